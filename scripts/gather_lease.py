"""A GPU lease's returned plan outputs gathered into one results file (benchmarks/results/), nothing recomputed.

    python scripts/gather_lease.py benchmarks/results/NAME.json arm=LANE1_DIR wind=LANE2_DIR \\
        --command "bash scripts/gpu/detached.sh ..." --code REV --device "nvidia-h100-x4 (...)" \\
        --question "..." [--data "..."] [--name transfer-paper=arm192-paper ...] [--fact held_s=1570.1 ...]

An input is a lane's returned folder (its queue.log beside queue.tgz and queue-2.tgz) or one queue tarball, with an
optional LABEL= in front. Every JSON a plan's steps left in $OUT goes in whole, sorted by what it is and keyed by its
file's stem (or by --name's new key):
- ``tables``: results of `clothgap eval ablation` and scripts/gpu/learn_grid.py (a ``recipes`` list), which
  scripts/plot_learning_curves.py reads as ``NAME.json:KEY``;
- ``paired``: scripts/pooled_recipes.py's comparisons (``acc_a_minus_b``);
- ``measured``: `clothgap eval measured` (``fabrics`` and ``models``). Its models carry their per-fabric rows as
  numbers (``per_fabric``); for a file without them, each model's per-fabric table is taken, as text, from the
  Markdown the same step wrote of the same stem, into ``measured_fabrics``;
- ``gpu_timings``: benchmarks/study.py --timings (``timings``);
- ``other``: any other JSON.
The same stem from two steps is kept once when the files are the same, else under ``STEP/STEM`` each. The queue
logs' step times go in ``queue_step_seconds`` per input, ``--fact KEY=VALUE`` adds what the logs do not hold (a
call's wall time, device time left), a value read as JSON where it parses. A path into the step's own output
folder (``/ANY/out/STEP/``, the machine's $OUT) is written as ``$OUT/``, as the plans' commands name it; files that
then differ in nothing else are kept once.
"""
from __future__ import annotations

import argparse
import json
import re
import tarfile
from pathlib import Path

KINDS = ("tables", "paired", "measured", "gpu_timings", "other")


def kind_of(doc) -> str:
    if isinstance(doc, dict):
        if isinstance(doc.get("recipes"), list):
            return "tables"
        if "acc_a_minus_b" in doc:
            return "paired"
        if "fabrics" in doc and "models" in doc:
            return "measured"
        if "timings" in doc:
            return "gpu_timings"
    return "other"


def fabric_tables(markdown: str) -> dict[str, list[dict[str, str]]]:
    """Each section's per-fabric rows (``| Fabric | ...``) of a `clothgap eval measured` Markdown, by section title."""
    out: dict[str, list[dict[str, str]]] = {}
    section, header = None, None
    for line in markdown.splitlines():
        if line.startswith("## "):
            section, header = line[3:].strip(), None
        elif section and line.startswith("| Fabric"):
            header = [c.strip() for c in line.strip().strip("|").split("|")]
        elif header and line.startswith("|") and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cells) == len(header):
                out.setdefault(section, []).append(dict(zip(header, cells)))
        elif not line.strip():
            header = None
    return out


def step_seconds(log: str) -> dict[str, float]:
    """The queue's ``== STEP: exit 0 after N s`` lines (steps that finished)."""
    return {m.group(1): float(m.group(2)) for m in re.finditer(r"^== (\S+): exit 0 after (\d+(?:\.\d+)?) s", log, re.M)}


def with_out_named(text: str, step: str) -> str:
    """``text`` with each path into the step's output folder (``/ANY/out/STEP/FILE``) as ``$OUT/FILE``."""
    # an absolute path only, starting where a value or a word starts (not inside a relative path or a URL)
    return re.sub(rf'(?<![^\s"\'=])(?:/[^\s"\'/]+)*/out/{re.escape(step)}/', "$OUT/", text)


def _members(tarball: Path):
    """(step, file name, bytes) of each regular file in a queue tarball (``./STEP/FILE``)."""
    try:
        with tarfile.open(tarball) as tar:
            for m in tar.getmembers():
                parts = Path(m.name).parts
                parts = parts[1:] if parts and parts[0] == "." else parts
                if m.isfile() and len(parts) == 2:
                    yield parts[0], parts[1], tar.extractfile(m).read()
    except (tarfile.TarError, OSError, EOFError) as e:
        raise SystemExit(f"gather_lease: cannot read {tarball}: {e}") from e


def _inputs(specs: list[str]):
    """(label, queue.log text or None, tarballs) of each input argument."""
    for spec in specs:
        label, sep, path = spec.partition("=")
        if not sep:
            label, path = "", spec
        p = Path(path)
        if p.is_dir():
            tarballs = sorted(p.glob("queue*.tgz"), key=lambda t: (len(t.name), t.name))   # queue.tgz, then -2
            log = p / "queue.log"
            if not tarballs and not log.is_file():
                raise SystemExit(f"gather_lease: {p} holds neither queue.log nor queue*.tgz")
            yield label or p.name, log.read_text(errors="replace") if log.is_file() else None, tarballs
        elif p.is_file():
            yield label or p.stem, None, [p]
        else:
            raise SystemExit(f"gather_lease: no such lane folder or tarball: {p}")


def gather(specs: list[str], renames: dict[str, str]) -> dict:
    found: dict[str, dict[str, list[tuple[str, bytes, object]]]] = {k: {} for k in KINDS}
    markdown: dict[tuple[str, str], str] = {}         # (step, stem): a measured JSON's tables are its step's
    steps: dict[str, dict[str, float]] = {}
    read: dict[str, list[str]] = {}          # what each input gave, by file name (no machine's paths)
    for label, log, tarballs in _inputs(specs):
        if log is not None:
            steps[label] = step_seconds(log)
        read[label] = (["queue.log"] if log is not None else []) + [t.name for t in tarballs]
        for tarball in tarballs:
            for step, name, data in _members(tarball):
                stem, suffix = Path(name).stem, Path(name).suffix
                if suffix == ".md":
                    markdown[step, stem] = data.decode(errors="replace")
                if suffix != ".json":
                    continue
                try:
                    data = with_out_named(data.decode(), step).encode()
                    doc = json.loads(data)
                except ValueError as e:         # UnicodeDecodeError too
                    raise SystemExit(f"gather_lease: {tarball}: {step}/{name} is not JSON ({e})") from e
                found[kind_of(doc)].setdefault(stem, []).append((step, data, doc))
    result: dict = {k: {} for k in KINDS}
    fabrics: dict[str, dict] = {}
    for kind, by_stem in found.items():
        for stem, copies in sorted(by_stem.items()):
            distinct: dict[bytes, tuple[str, object]] = {}
            for step, data, doc in copies:
                distinct.setdefault(data, (step, doc))      # the same bytes once, under the first step
            for step, doc in distinct.values():
                key = renames.get(stem, stem) if len(distinct) == 1 else f"{step}/{stem}"
                if key in result[kind]:
                    raise SystemExit(f"gather_lease: two {kind} files would both be {key!r}: rename one with --name")
                result[kind][key] = doc
                if (kind == "measured" and (step, stem) in markdown
                        and not all("per_fabric" in m for m in doc["models"])):    # rows as numbers: no text needed
                    fabrics[key] = fabric_tables(markdown[step, stem])
    result["measured_fabrics"] = fabrics
    result["queue_step_seconds"] = steps
    result["gathered_by"] = {"script": "scripts/gather_lease.py", "inputs": read, "names": renames}
    return {k: v for k, v in result.items() if v}


def _pairs(items: list[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"gather_lease: {what} takes KEY=VALUE, got {item!r}")
        out[key] = value
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("out", type=Path, help="the results JSON to write")
    ap.add_argument("inputs", nargs="+", help="[LABEL=]lane folder (queue.log, queue*.tgz) or queue tarball")
    ap.add_argument("--command", required=True, help="what ran on the GPU machine, as typed")
    ap.add_argument("--code", required=True, help="the commit it ran")
    ap.add_argument("--device", required=True, help="the machine, e.g. 'nvidia-h100-x4 (4 x H100 80GB HBM3)'")
    ap.add_argument("--date", help="the lease's date (YYYY-MM-DD)")
    ap.add_argument("--question", help="what the lease measured")
    ap.add_argument("--data", help="the data the plans made (settings, sizes, seeds, split)")
    ap.add_argument("--name", action="append", default=[], help="STEM=KEY: file stem STEM goes in as KEY")
    ap.add_argument("--fact", action="append", default=[], help="KEY=VALUE: a figure the logs do not hold")
    args = ap.parse_args(argv)
    facts = {}
    for key, value in _pairs(args.fact, "--fact").items():
        try:
            facts[key] = json.loads(value)
        except ValueError:
            facts[key] = value
    gathered = gather(args.inputs, _pairs(args.name, "--name"))
    head = {"command": args.command, "code": args.code, "date": args.date, "device": args.device,
            "question": args.question, "data": args.data}
    result = {k: v for k, v in head.items() if v is not None} | ({"facts": facts} if facts else {}) | gathered
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    counts = ", ".join(f"{len(gathered[k])} {k}" for k in (*KINDS, "measured_fabrics") if k in gathered)
    print(f"wrote {args.out}: {counts or 'nothing gathered'}")


if __name__ == "__main__":
    main()
