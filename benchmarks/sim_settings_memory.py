"""A simulating process's memory as it simulates one setting after another: whether it grows with the settings.

    python benchmarks/sim_settings_memory.py --motions wind,arm --rounds 4 --device cpu --out sim_mem.json

In this one process, simulates each motion's uniform1 setting in turn, ``--rounds`` times over (each setting a run
of its own in a scratch folder, the `paper` preset's simulation at ``--classes`` x ``--sequences``), and after each
records the process's resident memory and its private (anonymous) part, after a garbage collection. The sim stage
goes through a study's settings the same way in one process (issue 14: host memory flat across settings).
"""

from __future__ import annotations

import argparse
import gc
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.config import preset  # noqa: E402
from clothgap.runs import Run  # noqa: E402
from common import process_memory_mib, write_result  # noqa: E402  (benchmarks/common.py)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--motions", default="wind,arm", help="comma-separated, simulated in this order each round")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--classes", default="0,8,17,30", help="class indices (default: four)")
    ap.add_argument("--sequences", type=int, default=2, help="sequences a class (default 2)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)

    from sim.stage import run_sim

    motions = args.motions.split(",")
    classes = tuple(int(c) for c in args.classes.split(","))
    rows = [{"after": "start", **process_memory_mib()}]
    scratch = Path(tempfile.mkdtemp(prefix="sim-settings-memory-"))
    try:
        for k in range(args.rounds):
            for motion in motions:
                cfg = preset("paper")
                cfg = replace(cfg, sim=replace(cfg.sim, device=args.device, motions=(motion,), remeshing=("uniform1",),
                                               classes=classes, sequences_per_class=args.sequences))
                run = Run.create_or_resume(scratch / f"{k}-{motion}", cfg)
                summary = run_sim(run, progress=False)
                if summary["failed"]:
                    raise SystemExit(f"sim_settings_memory: {summary['failed']} clips of {motion} failed")
                shutil.rmtree(run.root, ignore_errors=True)
                gc.collect()
                rows.append({"after": f"{motion}-uniform1", "round": k, "clips": summary["simulated"],
                             **process_memory_mib()})
                print(rows[-1], file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    result = {"device": args.device, "motions": motions, "rounds": args.rounds, "classes": list(classes),
              "sequences_per_class": args.sequences, "rows": rows}
    write_result("sim_settings_memory.py", argv, result, args.out)


if __name__ == "__main__":
    main()
