"""Which clips the CG's iteration cap binds on, and what running them to tolerance would change.

    python benchmarks/sim_cg_cap.py [--setting wind-uniform1] [--frames 20] [--iterations 120]

Simulates a few ``paper``-preset clips of stiff and soft classes (CPU, self-collision as the preset has it)
at the stage's ``sim.cg_iterations`` and again at ``--iterations``, and reports per clip: iterations a step
(mean, max), the worst final relative residual, and how far the positions move between the two (mean and
max over vertices and frames, beside the clip's own mean displacement). Writes
benchmarks/results/sim_cg_cap-<setting>-cpu.json.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim.stage import simulate_scenes  # noqa: E402
from common import RESULTS, arguments, paper_scenes, simulate_options, write_result  # noqa: E402  (benchmarks/common.py)

CLIPS = (42, 49, 61, 96)   # classes 42, 49 (stiff stretching), 7 (soft), 42 again (another sequence)


def main(argv: list[str] | None = None) -> None:
    args = arguments(__doc__, argv, iterations=120)
    cfg, _, built = paper_scenes(args.setting, CLIPS)
    runs = {}
    for iterations in (cfg.cg_iterations, args.iterations):
        runs[iterations] = simulate_scenes([s for s, _ in built],
                                           **simulate_options(cfg, args.frames, cg_iterations=iterations))
    rows = []
    for k, (index, (_, labels)) in enumerate(zip(CLIPS, built)):
        capped, full = runs[cfg.cg_iterations][k], runs[args.iterations][k]
        moved = np.linalg.norm(capped.positions - full.positions, axis=-1)
        motion = np.linalg.norm(full.positions - full.positions[0], axis=-1).mean()
        row = {"clip_index": index, "class_index": labels["class_index"], "p": labels["p"], "k": labels["k"]}
        for name, r in (("capped", capped), ("to_tolerance", full)):
            row[name] = {"cap": cfg.cg_iterations if name == "capped" else args.iterations,
                         "iterations_per_step": round(r.cg.iterations / r.cg.steps, 1),
                         "iterations_max": r.cg.max_iterations,
                         "worst_relative_residual": float(f"{r.cg.max_residual:.3g}")}
        row["positions_moved_mm"] = {"mean": round(1000 * float(moved.mean()), 3),
                                     "max": round(1000 * float(moved.max()), 2)}
        row["clip_mean_displacement_mm"] = round(1000 * float(motion), 1)
        rows.append(row)
        print(json.dumps(row), flush=True)
    result = {"setting": args.setting, "frames": args.frames, "cg_iterations": cfg.cg_iterations,
              "cg_tolerance": cfg.cg_tolerance, "self_collision": cfg.self_collision, "clips": rows}
    write_result("sim_cg_cap.py", argv, result, args.out or RESULTS / f"sim_cg_cap-{args.setting}-cpu.json")

if __name__ == "__main__":
    main()
