"""The import graph keeps its floors (docs/architecture.md): read from the source with ``ast``, nothing imported.

Ground (``GROUND``) imports no stage and nothing of the top floor; a stage imports the ground, itself and the
stages below it (sim < render < learn < eval) and nothing of the top floor; module-level imports form no cycle.
Imports inside functions count for the floors too (they only defer a heavy dependency, they do not lift a floor).
No function of those packages is longer than ``MAX_FUNCTION_LINES`` (Warp kernels aside).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
STAGES = ("sim", "render", "learn", "eval")             # in order: each may import the ones before it
GROUND = {"clothgap", "clothgap.errors", "clothgap.checks", "clothgap.seeding", "clothgap.files", "clothgap.settings",
          "clothgap.runs", "clothgap.parallel"}
# The top floor: it alone knows every stage. ``<package>.__main__`` modules are entry points, top floor too.
TOP = {"clothgap.config", "clothgap.api", "clothgap.cli", "clothgap.executor", "clothgap.cuda_mps", "clothgap.__main__"}


def modules(root: Path) -> dict[str, Path]:
    """Dotted name -> file of every module of the library packages under ``root``."""
    out = {}
    for package in ("clothgap", *STAGES):
        for path in sorted((root / package).rglob("*.py")):
            name = ".".join(path.relative_to(root).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def imports(name: str, path: Path, known: dict[str, Path]) -> list[tuple[str, int, bool]]:
    """``(imported module, line, inside a function)`` for each import of a project module in ``path``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []

    def resolve(dotted: str) -> str | None:
        while dotted and dotted not in known:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                targets = [resolve(alias.name) for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    parts = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = ".".join(parts + ([base] if base else []))
                # ``from pkg import mod`` imports the module pkg.mod; ``from mod import name`` the module mod
                targets = [resolve(f"{base}.{alias.name}") for alias in child.names]
            else:
                visit(child, inner)
                continue
            found.extend((t, child.lineno, inner) for t in dict.fromkeys(targets) if t and t != name)

    visit(ast.parse(path.read_text(), str(path)), False)
    return found


def floor(name: str) -> str:
    """"ground", "top", a stage's name, or "unplaced" (a clothgap module this test does not know yet)."""
    if name in TOP or name.endswith(".__main__"):
        return "top"
    if name in GROUND:
        return "ground"
    package = name.partition(".")[0]
    return package if package in STAGES else "unplaced"


def upward(source: str, target: str) -> str | None:
    """Why ``source`` may not import ``target``, or None when it may."""
    a, b = floor(source), floor(target)
    if "unplaced" in (a, b):
        return f"{source if a == 'unplaced' else target} has no floor: add it to GROUND or TOP in this test"
    if a == "top" or b == "ground":
        return None
    if a == "ground":
        return f"the ground floor imports {'the top floor' if b == 'top' else 'stage ' + b}"
    if b == "top":
        return f"stage {a} imports the top floor"
    if STAGES.index(b) > STAGES.index(a):
        return f"stage {a} imports the later stage {b}"
    return None


def violations(root: Path) -> list[str]:
    known = modules(root)
    out = []
    for name, path in known.items():
        for target, line, in_function in imports(name, path, known):
            why = upward(name, target)
            if why:
                where = "in a function" if in_function else "at module level"
                out.append(f"{name} -> {target} ({path.relative_to(root)}:{line}, {where}): {why}")
    return out


def cycles(root: Path) -> list[list[str]]:
    """Cycles among module-level imports, each as the path of modules that closes it."""
    known = modules(root)
    graph = {name: sorted({t for t, _, inner in imports(name, path, known) if not inner})
             for name, path in known.items()}
    found, state = [], {}           # state: 1 on the current path, 2 finished
    path: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        path.append(node)
        for nxt in graph[node]:
            if state.get(nxt) == 1:
                found.append(path[path.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt)
        path.pop()
        state[node] = 2

    for node in graph:
        if node not in state:
            visit(node)
    return found


def test_no_import_reaches_up_a_floor():
    bad = violations(ROOT)
    assert not bad, "imports against the floors (docs/architecture.md):\n  " + "\n  ".join(bad)


def test_module_level_imports_form_no_cycle():
    found = cycles(ROOT)
    assert not found, "import cycles:\n  " + "\n  ".join(" -> ".join(c) for c in found)


def test_the_checks_name_the_offending_edge(tmp_path):
    # A tree with one import of each kind the floors forbid, and one allowed: the checks must name each bad one.
    files = {
        "clothgap/__init__.py": "",
        "clothgap/runs.py": "from clothgap.errors import ConfigError\nfrom sim import stage\n",
        "clothgap/errors.py": "def f():\n    import clothgap.cli\n",
        "clothgap/cli.py": "import eval.stage\n",
        "sim/__init__.py": "",
        "sim/stage.py": "from . import solver\n\ndef run():\n    from render.stage import render\n",
        "sim/solver.py": "from sim.stage import run\n",
        "render/__init__.py": "",
        "render/stage.py": "from sim.stage import run\nfrom clothgap.config import StudyConfig\n",
        "learn/__init__.py": "",
        "eval/__init__.py": "",
        "eval/stage.py": "import render.stage, learn\n",
        "clothgap/config.py": "",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    bad = violations(tmp_path)
    assert len(bad) == 4, bad
    assert any(b.startswith("clothgap.runs -> sim.stage (clothgap/runs.py:2, at module level): the ground floor")
               for b in bad)
    assert any(b.startswith("clothgap.errors -> clothgap.cli") and "in a function" in b for b in bad)
    assert any(b.startswith("sim.stage -> render.stage") and "later stage render" in b for b in bad)
    assert any(b.startswith("render.stage -> clothgap.config") and "top floor" in b for b in bad)
    (cycle,) = cycles(tmp_path)
    assert cycle[0] == cycle[-1] and set(cycle) == {"sim.stage", "sim.solver"}


# ---------------------------------------------------------------- short functions

MAX_FUNCTION_LINES = 80     # a longer function is split into named steps (docs/architecture.md)


def _is_warp_kernel(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """Decorated with ``wp.kernel`` or ``wp.func`` (with or without arguments): Warp compiles it whole."""
    for decorator in node.decorator_list:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        if ast.unparse(target) in ("wp.kernel", "wp.func", "warp.kernel", "warp.func"):
            return True
    return False


def long_functions(root: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``file:line name (N lines)`` for every function of the library packages longer than ``limit`` lines
    (nested functions count within the function around them too), Warp kernels left out."""
    out = []
    for name, path in modules(root).items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not _is_warp_kernel(node):
                lines = node.end_lineno - node.lineno + 1
                if lines > limit:
                    out.append(f"{path.relative_to(root)}:{node.lineno} {node.name} ({lines} lines)")
    return out


def test_no_library_function_is_longer_than_the_limit():
    found = long_functions(ROOT)
    assert not found, (f"functions over {MAX_FUNCTION_LINES} lines (split them into named steps):\n  "
                       + "\n  ".join(found))


def test_the_length_check_names_a_long_function_and_spares_warp_kernels(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES))
    (tmp_path / "sim").mkdir()
    (tmp_path / "sim" / "long.py").write_text(
        f"def long():\n{body}\n\n@wp.kernel\ndef kernel():\n{body}\n\n@wp.func\ndef helper():\n{body}\n\n"
        f"@wp.kernel(enable_backward=False)\ndef kernel2():\n{body}\n\ndef short():\n    return 1\n")
    assert long_functions(tmp_path) == [f"sim/long.py:1 long ({MAX_FUNCTION_LINES + 1} lines)"]
