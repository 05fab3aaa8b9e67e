"""Scoring a run's models on the measured fabrics, in one process against a spawned pool (``eval.measured``).

    python benchmarks/measured_scoring.py RUN [--processes N] [--repeats 2] [--out FILE]
    python benchmarks/measured_scoring.py RUN --baseline REV [--repeats 3] [--out FILE]

RUN is a run folder with finished models whose measured clips are already simulated and rendered (``clothgap eval
measured RUN`` made them once). Every model's measured folder is removed before each scoring, so each model is
predicted and scored again: its copy of the clips at its image size, the network, its figures and its bootstraps,
the part of ``clothgap eval`` that grows with the number of models (48 in the `study` preset). One process and a
pool of ``--processes`` (default ``eval.measured.scorer_processes`` of this host, at least 2) alternate,
``--repeats`` times each; the tables of both are compared byte for byte.

With ``--baseline REV`` it times one process's scoring with this tree's ``eval`` package against REV's
(``git archive``), each in a fresh process, either first in turn, and compares their tables and every model's
per-clip predictions byte for byte.

Writes benchmarks/results/measured_scoring-<host>-m<models>.json (``--baseline``: measured_scoring_baseline-...)
with the command.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, ROOT, either_first, extract_revision, git, tree_label, write_result  # noqa: E402
import clothgap.config  # noqa: E402,F401  (registers the study config a run folder is read with)
from clothgap.parallel import host_processes  # noqa: E402
from clothgap.runs import Run  # noqa: E402
from eval.measured import resolve, run_measured, scorer_processes  # noqa: E402
from eval.trained import finished_models  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--processes", type=int, default=None, help="pool size (default: this host's scorer_processes)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--baseline", default=None, metavar="REV",
                    help="time one process with this tree's eval/ against REV's instead of one process against a pool")
    args = ap.parse_args(argv)

    run = Run.open(args.run)
    models = finished_models(run)
    if len(models) < 2:
        raise SystemExit(f"{args.run} has {len(models)} finished model(s); the comparison needs two or more")
    sequences, fabrics, variant = resolve(run)
    if args.baseline:
        return against_baseline(args, argv, run, len(models), sequences, fabrics, variant)
    processes = args.processes or max(2, scorer_processes(len(models)))
    run_measured(run, models=models, progress=False, processes=0)     # the clips made (or found) before timing

    seconds: dict[str, list[float]] = {"one_process": [], "pool": []}
    tables: dict[str, str] = {}
    for _ in range(args.repeats):
        for way, n in (("one_process", 0), ("pool", processes)):
            shutil.rmtree(run.eval_dir / "measured" / variant, ignore_errors=True)
            t0 = time.perf_counter()
            out = run_measured(run, models=models, progress=False, processes=n)
            seconds[way].append(round(time.perf_counter() - t0, 2))
            assert out["predicted"] == len(models), out
            text = (run.eval_dir / "measured.csv").read_text() + (run.eval_dir / "measured_correlations.csv").read_text()
            if tables.setdefault(way, text) != text:
                raise SystemExit(f"{way}: the tables differ between repeats")
            print(f"{way}: {seconds[way][-1]} s", flush=True)
    median = {way: statistics.median(s) for way, s in seconds.items()}
    result = {
        "host": platform.node(), "cpus": host_processes(), "run": str(args.run), "models": len(models),
        "fabrics": len(fabrics), "sequences": sequences, "variant": variant, "processes": processes,
        "seconds": seconds, "median_s": median,
        "speedup": round(median["one_process"] / median["pool"], 2),
        "same_tables": tables["one_process"] == tables["pool"],
    }
    write_result("measured_scoring.py", argv, result, args.out or _result_path("measured_scoring", len(models)))
    if not result["same_tables"]:
        raise SystemExit("the pool's tables differ from one process's")


# One process's scoring of every finished model, timed in the process; prints the seconds and a digest of the tables
# and every model's per-clip predictions.
TIMER = """
import hashlib, sys, time
import clothgap.config
from clothgap.runs import Run
from eval.measured import run_measured
from eval.trained import finished_models
run = Run.open(sys.argv[1])
models = finished_models(run)
t0 = time.perf_counter()
out = run_measured(run, models=models, progress=False, processes=0)
seconds = time.perf_counter() - t0
assert out["predicted"] == len(models), out
digest = hashlib.sha256()
for path in [run.eval_dir / "measured.csv", run.eval_dir / "measured_correlations.csv",
             *sorted(p for p in (run.eval_dir / "measured").rglob("videos.csv")
                     if not p.parent.name.startswith("ensemble-"))]:      # (a seeds' ensemble: not every revision has)
    digest.update(path.read_bytes())
print(seconds, digest.hexdigest())
"""


def against_baseline(args, argv, run, models: int, sequences: int, fabrics, variant: str) -> None:
    baseline_rev = git("rev-parse", "--short", args.baseline)
    tree = tree_label("eval")
    run_measured(run, progress=False, processes=0)      # the clips made (or found) before timing
    seconds: dict[str, list[float]] = {"baseline": [], "this_tree": []}
    digests: dict[str, set[str]] = {"baseline": set(), "this_tree": set()}
    with tempfile.TemporaryDirectory() as tmp:
        base = extract_revision(args.baseline, Path(tmp), "eval")
        for name, root in either_first((("baseline", base), ("this_tree", ROOT)), args.repeats):
            shutil.rmtree(run.eval_dir / "measured" / variant, ignore_errors=True)
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys([str(root), str(ROOT)]))}
            done = subprocess.run([sys.executable, "-c", TIMER, str(run.root)], capture_output=True, text=True,
                                  env=env, cwd=root)
            if done.returncode:
                raise SystemExit(f"{name}'s scoring failed:\n{done.stderr[-4000:]}")
            out = done.stdout.split()
            seconds[name].append(round(float(out[-2]), 2))
            digests[name].add(out[-1])
            print(f"{name}: {seconds[name][-1]} s", flush=True)
    median = {name: statistics.median(s) for name, s in seconds.items()}
    result = {
        "host": platform.node(), "cpus": host_processes(), "run": str(args.run), "models": models,
        "fabrics": len(fabrics), "sequences": sequences, "variant": variant, "processes": 0,
        "baseline": baseline_rev, "this_tree": tree, "seconds": seconds, "median_s": median,
        "speedup": round(median["baseline"] / median["this_tree"], 2),
        "same_tables": digests["baseline"] == digests["this_tree"] and len(digests["baseline"]) == 1,
    }
    write_result("measured_scoring.py", argv, result, args.out or _result_path("measured_scoring_baseline", models))
    if not result["same_tables"]:
        raise SystemExit("this tree's tables or predictions differ from the baseline's")


def _result_path(name: str, models: int) -> Path:
    """benchmarks/results/NAME-<cpu|cuda><CPUs>-m<models>.json"""
    import torch

    return RESULTS / f"{name}-{'cuda' if torch.cuda.is_available() else 'cpu'}{host_processes()}-m{models}.json"


if __name__ == "__main__":
    main()
