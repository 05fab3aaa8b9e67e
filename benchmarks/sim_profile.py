"""Where a simulation step's GPU time goes: per-kernel times of the solver at the paper's batch.

    python benchmarks/sim_profile.py --device cuda --n 2592 [--setting wind-uniform1] [--steps 20]

Builds the ``paper`` preset's scenes for the first ``--n`` clips of a setting (self-collision as
the preset has it), settles them, then times ``--steps`` steps twice: as the stage runs them (one
CUDA graph per step; wall time with a device sync) and launch by launch
(``BatchSolver.step_uncaptured``) under ``wp.ScopedTimer(cuda_filter=wp.TIMING_KERNEL)``, which
gives each kernel's GPU time (on a CPU each launch's wall time, which is its kernel's). Writes benchmarks/results/sim_profile-<device>-<setting>-n<N>.json
(kernels sorted by total time, with the command).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import warp as wp

from clothgap.config import PRESETS
from sim.solver import resolve_device
from sim.stage import build_scene, parse_setting, setting_simulator, settled_solver


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--n", type=int, default=2592)
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    device = resolve_device(args.device)
    cfg = PRESETS["paper"]().sim
    setting = parse_setting(args.setting)
    if setting.remeshing == "adaptive":
        sys.exit("error: adaptive settings remesh between frames; profile a uniform setting")
    mesh, _ = setting_simulator(cfg, setting)
    scenes = [build_scene(cfg, 0, i, setting, mesh)[0] for i in range(args.n)]
    solver = settled_solver(scenes, fps=cfg.fps, substeps=cfg.substeps, settle_s=cfg.settle_s,
                            cg_iterations=cfg.cg_iterations, cg_tolerance=cfg.cg_tolerance,
                            self_collision=cfg.self_collision, collision_thickness=cfg.collision_thickness,
                            device=device)
    solver.step(1)                                        # capture, compile
    # As the stage steps: one CUDA graph per step on a GPU (all CG iterations), the host loop on a CPU.
    wp.synchronize_device(device)
    start = time.perf_counter()
    solver.step(args.steps)
    wp.synchronize_device(device)
    stage_ms = (time.perf_counter() - start) / args.steps * 1e3
    solver.step_uncaptured(1)                             # warm the host path
    per_kernel: dict[str, list[float]] = defaultdict(list)
    if wp.get_device(device).is_cuda:
        with wp.ScopedTimer("steps", print=False, synchronize=True, cuda_filter=wp.TIMING_KERNEL) as timer:
            solver.step_uncaptured(args.steps)
        for r in timer.timing_results:
            per_kernel[r.name].append(r.elapsed)
        uncaptured_ms = timer.elapsed
    else:                     # CPU launches run to completion: each launch's wall time is its kernel's
        host: dict[str, list[float]] = {}
        start = time.perf_counter()
        solver.step_uncaptured(args.steps, host_times=host)
        uncaptured_ms = (time.perf_counter() - start) * 1e3
        for name, seconds in host.items():
            per_kernel[name] = [1e3 * x for x in seconds]
    kernels = sorted(({"kernel": k, "ms_per_step": round(sum(v) / args.steps, 4), "launches_per_step": len(v) / args.steps,
                       "ms_per_launch": round(sum(v) / len(v), 5)} for k, v in per_kernel.items()),
                     key=lambda row: -row["ms_per_step"])
    total = sum(row["ms_per_step"] for row in kernels)
    result = {"command": "python " + " ".join(sys.argv), "platform": platform.platform(), "device": device,
              "gpu": wp.get_device(device).name, "setting": args.setting, "clips": args.n,
              "vertices": int(solver.vertex_offsets[-1]), "steps_timed": args.steps,
              "cg_iterations": cfg.cg_iterations, "self_collision": cfg.self_collision,
              "stage_ms_per_step": round(stage_ms, 3), "kernel_ms_per_step": round(total, 3),
              "uncaptured_wall_ms_per_step": round(uncaptured_ms / args.steps, 3),
              "steps_per_setting": int(round(cfg.settle_s * cfg.fps * cfg.substeps)) + cfg.frames * cfg.substeps,
              "kernels": kernels}
    out = args.out or Path(__file__).parent / "results" / f"sim_profile-{device.split(':')[0]}-{args.setting}-n{args.n}.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "kernels"}, indent=2))
    for row in kernels[:15]:
        print(f"{row['ms_per_step']:9.3f} ms/step  {row['launches_per_step']:6.1f} launches  {row['kernel']}")


if __name__ == "__main__":
    main()
