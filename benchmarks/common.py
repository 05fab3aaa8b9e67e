"""What the benchmarks share: the paper preset's sim settings on the CPU, writing a result with its command, and
timing this tree against a baseline revision's code."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import clothgap.config as study_config  # noqa: E402
from clothgap.settings import apply_overrides  # noqa: E402
from sim.stage import build_scene, parse_setting, setting_simulator  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def paper_sim_cpu():
    """The ``paper`` preset's sim settings with the simulation on the CPU."""
    return apply_overrides(study_config.preset("paper"), ["sim.device=cpu"]).sim


def frame_set_arguments(ap: argparse.ArgumentParser, clips: int = 2592) -> None:
    """The arguments of the benchmarks that write a setting's frames: --clips (default ``clips``), --frames and
    --size (the `paper` preset's 40 and 112), --workdir (where their stand-in files go) and --out."""
    ap.add_argument("--clips", type=int, default=clips)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--size", type=int, default=112)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()))
    ap.add_argument("--out", type=Path, default=None)


def write_result(script: str, argv: list[str] | None, result: dict, out: Path | None) -> None:
    """Writes ``result`` (JSON) to ``out`` with the command that made it first, and says where; without ``out``
    prints it."""
    command = f"python benchmarks/{script} " + " ".join(argv if argv is not None else sys.argv[1:])
    text = json.dumps({"command": command.strip(), **result}, indent=2)
    if out is None:
        print(text)
        return
    out.write_text(text + "\n")
    print(f"wrote {out}")


def process_memory_mib() -> dict[str, int]:
    """This process's resident memory and its private (anonymous) part, MiB (Linux: /proc/self/status)."""
    status = Path("/proc/self/status").read_text()
    return {key: int(re.search(rf"{field}:\s+(\d+)", status).group(1)) // 1024
            for key, field in (("resident_mib", "VmRSS"), ("anon_mib", "RssAnon"))}


def git(*words: str) -> str:
    """A git command's output in this checkout."""
    return subprocess.run(["git", *words], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()


def extract_revision(rev: str, dest: Path, *paths: str) -> Path:
    """``paths`` (default: every tracked file) as they are at revision ``rev``, extracted into ``dest`` (git
    archive); returns ``dest``, a tree to put first on a fresh process's PYTHONPATH."""
    dest.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "archive", rev, *paths], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def tree_label(*paths: str) -> str:
    """This checkout's commit, and whether ``paths`` have changes not committed."""
    changed = git("status", "--porcelain", *paths)
    return git("rev-parse", "--short", "HEAD") + (f" with changes to {', '.join(paths)}" if changed else "")


def either_first(pair: Sequence, repeats: int) -> Iterator:
    """The two items of ``pair``, ``repeats`` times, the first first in even repeats and second in odd ones (so
    neither side always runs on a warmer machine)."""
    for repeat in range(repeats):
        yield from (pair if repeat % 2 == 0 else pair[::-1])


def torch_device(device) -> dict:
    """What a training benchmark's result says of where it ran: the device's name and torch's version."""
    import torch

    return {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
            "torch": torch.__version__}


def run_arguments(doc: str, *, recipe: str | None = None, model: str = "lrcn",
                  model_help: str | None = None) -> argparse.ArgumentParser:
    """The training benchmarks' parser: a run folder, --setting, --variant, --model and, when given a default,
    --recipe (an ``eval.ablation`` recipe whose train settings it uses)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--variant", default="paper")
    if recipe is not None:
        ap.add_argument("--recipe", default=recipe, help="an eval.ablation recipe (its train settings)")
    ap.add_argument("--model", default=model, help=model_help)
    return ap


def simulate_options(cfg, frames: int, device: str = "cpu", **changes) -> dict:
    """The keyword arguments of a batch simulator (``sim.stage.simulate_scenes`` or its adaptive form) for sim
    settings ``cfg``, ``frames`` frames on ``device``; ``changes`` replace any of them."""
    return {"fps": cfg.fps, "frames": frames, "substeps": cfg.substeps, "settle_s": cfg.settle_s,
            "cg_iterations": cfg.cg_iterations, "cg_tolerance": cfg.cg_tolerance,
            "self_collision": cfg.self_collision, "collision_thickness": cfg.collision_thickness,
            "device": device, **changes}


def paper_scenes(setting_name: str, indices) -> tuple:
    """The ``paper`` preset's sim settings on the CPU, the setting's batch simulator (``simulate_scenes`` or its
    adaptive form) and the (scene, labels) of each clip index."""
    cfg = paper_sim_cpu()
    setting = parse_setting(setting_name)
    mesh, simulate = setting_simulator(cfg, setting)
    return cfg, simulate, [build_scene(cfg, 0, i, setting, mesh) for i in indices]


def arguments(doc: str, argv: list[str] | None, **counts: int) -> argparse.Namespace:
    """The CG benchmarks' options: --setting, --frames, --out, and an integer option per ``counts`` entry."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--frames", type=int, default=20)
    for name, default in counts.items():
        ap.add_argument(f"--{name}", type=int, default=default)
    ap.add_argument("--out", type=Path)
    return ap.parse_args(argv)
