"""The CG's preconditioners on the same clips: iterations a step, clips at the cap, worst residual, seconds.

    python benchmarks/sim_preconditioner.py [--setting wind-uniform1] [--clips 32] [--frames 20]

Builds the ``paper`` preset's scenes (every 7th clip index, so the classes spread), settles them and records
``--frames`` frames once per preconditioner (``SolverParams.cg_preconditioner``), on the CPU. The CG statistics
cover the settling too. Writes benchmarks/results/sim_preconditioner-<setting>-n<N>-cpu.json with the command,
and the positions' difference between the two at the end.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, arguments, paper_scenes, write_result  # noqa: E402  (benchmarks/common.py)
from sim.solver import BatchSolver, SolverParams  # noqa: E402


def measure(scenes, cfg, preconditioner: str, frames: int) -> tuple[dict, np.ndarray]:
    dt = 1.0 / (cfg.fps * cfg.substeps)
    params = replace(SolverParams(dt=dt, cg_iterations=cfg.cg_iterations, cg_tolerance=cfg.cg_tolerance,
                                  self_collision=cfg.self_collision, collision_thickness=cfg.collision_thickness),
                     cg_preconditioner=preconditioner)
    solver = BatchSolver([s.spec for s in scenes], params, "cpu")
    solver.step(1)                              # compiles (after a kernel change) outside the timing
    solver.step(int(round(cfg.settle_s / dt)) - 1)
    solver.set_wind(np.stack([s.wind for s in scenes]))
    start = time.perf_counter()
    solver.step(frames * cfg.substeps)
    seconds = time.perf_counter() - start
    cg = solver.cg_stats()
    per_step = np.array([c.iterations / c.steps for c in cg])
    worst = np.array([c.max_residual for c in cg])
    row = {"preconditioner": preconditioner, "seconds_recording": round(seconds, 2),
           "iterations_per_step_mean": round(float(per_step.mean()), 2),
           "clips_at_the_cap": round(float(np.mean([c.max_iterations >= cfg.cg_iterations for c in cg])), 3),
           "worst_relative_residual_median": float(f"{np.median(worst):.4g}"),
           "worst_relative_residual_max": float(f"{worst.max():.4g}")}
    return row, np.stack(solver.positions())


def main(argv: list[str] | None = None) -> None:
    args = arguments(__doc__, argv, clips=32)
    cfg, _, built = paper_scenes(args.setting, range(0, 7 * args.clips, 7))
    scenes = [scene for scene, _ in built]
    rows, positions = [], {}
    for name in ("jacobi", "block"):
        row, positions[name] = measure(scenes, cfg, name, args.frames)
        rows.append(row)
        print(json.dumps(row), flush=True)
    moved = np.linalg.norm(positions["block"] - positions["jacobi"], axis=2)
    result = {"machine": platform.platform(), "setting": args.setting, "clips": args.clips, "frames": args.frames,
              "cg_iterations": cfg.cg_iterations, "cg_tolerance": cfg.cg_tolerance,
              "self_collision": cfg.self_collision, "rows": rows,
              "positions_block_vs_jacobi_m": {"mean": float(f"{moved.mean():.3g}"), "max": float(f"{moved.max():.3g}")}}
    write_result("sim_preconditioner.py", argv, result,
                 args.out or RESULTS / f"sim_preconditioner-{args.setting}-n{args.clips}-cpu.json")

if __name__ == "__main__":
    main()
