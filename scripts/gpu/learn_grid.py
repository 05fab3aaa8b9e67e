"""GPU: several recipes' models trained side by side over the machine's GPUs in one pool, then their tables.

    python3 scripts/gpu/learn_grid.py RUN --setting wind-uniform1 --parallel 6 --deadline 540 \\
        --job best:lrcn,base1,base2,base3 --job best+train_fraction=0.5:lrcn \\
        --table models-wind-uniform1=best:lrcn,base1,base2,base3 \\
        --table datasize-wind-uniform1=best,best+train_fraction=0.5:lrcn

``--job RECIPES:MODELS`` adds every recipe x model (x the recipe's seeds) to one training grid, trained
``--parallel`` at a time by ``clothgap.executor.run_train_parallel`` (round robin over the visible GPUs, base2
after its base1). Unlike ``eval ablation --parallel`` the recipes need not share their models, so a Table 3
row and lrcn-only levers fill the GPUs together. Training runs in its own process group, stopped at
``--deadline`` seconds; every model resumes epoch by epoch, so the same command again goes on where it
stopped (exit status 0; 1 when a model failed). ``--table NAME=RECIPES:MODELS`` then writes ``RUN/eval/NAME.{json,md}`` (``clothgap eval ablation``'s
tables, the first recipe the reference) once every model it needs is finished, and copies them to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path


def _recipes_models(text: str) -> tuple[list[str], list[str]]:
    recipes, sep, models = text.rpartition(":")
    if not sep or not recipes or not models:
        raise SystemExit(f"{text!r}: expected RECIPE[,RECIPE...]:MODEL[,MODEL...]")
    return recipes.split(","), models.split(",")


def _grid(run, setting: str, variant: str, jobs: list[str]) -> list[tuple]:
    from eval.ablation import ablation_grid

    grid: list[tuple] = []
    for job in jobs:
        recipes, models = _recipes_models(job)
        grid += [e for e in ablation_grid(run, setting, variant, recipes, models) if e not in grid]
    return grid


def _train(args, run) -> None:
    from clothgap.executor import ExecutorOptions, run_train_parallel

    grid = _grid(run, args.setting, args.variant, args.job)
    print(f"training {len(grid)} models, {args.parallel} at a time"
          f"{' under a CUDA MPS daemon' if args.cuda_mps == 'on' else ''}", flush=True)
    options = ExecutorOptions("process", workers=args.parallel, cuda_mps="on") if args.cuda_mps == "on" else None
    run_train_parallel(run, grid, args.parallel, options=options)


def _train_with_deadline(args) -> bool | None:
    """Training in a child process group: True when it finished before the deadline, False when the deadline
    stopped it, None when it failed. Stopping this process (SIGTERM, Ctrl-C) stops the group too."""
    argv = [sys.executable, __file__, "--train-only", *sys.argv[1:]]
    child = subprocess.Popen(argv, start_new_session=True)

    def stop_group(signum=None, _frame=None) -> None:
        try:
            os.killpg(child.pid, signal.SIGTERM)
            child.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
        except ProcessLookupError:
            pass
        if signum is not None:
            sys.exit(128 + signum)

    signal.signal(signal.SIGTERM, stop_group)
    signal.signal(signal.SIGINT, stop_group)
    try:
        return True if child.wait(timeout=args.deadline) == 0 else None
    except subprocess.TimeoutExpired:
        print(f"deadline: training stopped after {args.deadline:.0f} s; the same command resumes it", flush=True)
        stop_group()
        return False


def _tables(args, run) -> None:
    from eval.ablation import ablation_grid, recipe_root, run_ablation
    from learn.train import train_folder

    for spec in args.table:
        name, sep, body = spec.partition("=")
        if not sep:
            raise SystemExit(f"--table {spec!r}: expected NAME=RECIPES:MODELS")
        recipes, models = _recipes_models(body)
        missing = [e for e in ablation_grid(run, args.setting, args.variant, recipes, models)
                   if not (train_folder(run, *e[:4], root=recipe_root(run, e[4])) / "DONE").is_file()]
        if missing:
            print(f"table {name}: {len(missing)} model(s) not finished yet, e.g. {missing[0][4]}/{missing[0][2]}")
            continue
        run_ablation(run, args.setting, args.variant, recipes, models, name=name, progress=False,
                     test_variants=args.test_variant)
        md = run.eval_dir / f"{name}.md"
        print(md.read_text(), flush=True)
        if args.out:
            for suffix in (".json", ".md"):
                shutil.copy2(run.eval_dir / f"{name}{suffix}", Path(args.out) / f"{name}{suffix}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--variant", default="paper")
    ap.add_argument("--job", action="append", default=[], metavar="RECIPES:MODELS")
    ap.add_argument("--table", action="append", default=[], metavar="NAME=RECIPES:MODELS")
    ap.add_argument("--test-variant", action="append", default=[], metavar="VARIANT",
                    help="also score the tables' recipes on the test clips rendered in this look (e.g. heldout)")
    ap.add_argument("--parallel", type=int, default=4)
    ap.add_argument("--deadline", type=float, default=540.0, help="seconds of training in this call")
    ap.add_argument("--out", default=os.environ.get("OUT"), help="copy the tables here (default: $OUT)")
    ap.add_argument("--cuda-mps", choices=("off", "on"), default="off",
                    help="train the models sharing a GPU under a private CUDA MPS daemon (clothgap.cuda_mps)")
    ap.add_argument("--train-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()

    import clothgap.config  # noqa: F401  (registers the study config that Run.open reads)
    from clothgap.runs import Run

    run = Run.open(args.run)
    if args.table:
        from clothgap.errors import ConfigError
        from eval.ablation import require_test_clips

        try:
            require_test_clips(run, args.setting)  # before the GPU time that no table could use
        except ConfigError as e:
            raise SystemExit(f"learn_grid: {e}") from None
    if args.train_only:
        _train(args, run)
        return
    t0 = time.perf_counter()
    finished = _train_with_deadline(args) if args.job else True
    state = {True: "finished", False: "to be resumed", None: "FAILED (the first error is above)"}[finished]
    print(f"training call: {time.perf_counter() - t0:.0f} s, {state}", flush=True)
    _tables(args, run)
    if finished is None:
        sys.exit(1)


if __name__ == "__main__":
    main()
