"""Whether the graphed reader step (train.reader_graphs, the `paper` preset's) holds on this machine: its GPU tests
passed and, for every reader timed by benchmarks/reader_step.py, the step was captured and at least ``--min`` times
the eager one-batch step. Says which, and why not (exit 1: a plan's step that fails is recorded and the plan goes
on). ``--off FILE`` is removed when they hold and written (with why) when not: scripts/gpu/table3_shared.sh then
trains the readers eagerly (the plans write it before the check, so a check that never finishes leaves it too).

    python scripts/gpu/reader_graphs_ok.py RESULT.json... --tests-ok FILE [--off FILE] [--min 1.2]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def verdict(results: list[dict], tests_passed: bool, minimum: float) -> tuple[bool, str]:
    """(use the graphs, why) from reader_step results and whether the GPU tests passed."""
    if not tests_passed:
        return False, "the GPU tests did not pass"
    if not results:
        return False, "no reader was timed"
    for r in results:
        graphed = r.get("graphed")
        if not graphed or not graphed.get("captured"):
            return False, f"{r.get('model')}: not captured ({(graphed or {}).get('capture_failed')})"
        if r.get("graphed_over_one_batch", 0) < minimum:
            return False, f"{r['model']}: graphed {r.get('graphed_over_one_batch')}x the eager step, under {minimum}x"
    return True, ", ".join(f"{r['model']} {r['graphed_over_one_batch']}x" for r in results)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="*", type=Path)
    ap.add_argument("--tests-ok", type=Path, required=True, help="the file the GPU tests' step leaves when they pass")
    ap.add_argument("--off", type=Path, help="removed when the graphs hold, else written with why")
    ap.add_argument("--min", type=float, default=1.2)
    args = ap.parse_args(argv)
    results = [json.loads(p.read_text()) for p in args.results if p.is_file()]
    ok, why = verdict(results, args.tests_ok.is_file(), args.min)
    if args.off:
        args.off.unlink(missing_ok=True)
        if not ok:
            args.off.write_text(why + "\n")
    print(f"reader graphs {'hold' if ok else 'do not hold'}: {why}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
