"""Sim throughput: a batch of N wind clips in one solver vs the same code one clip at a time.

    python benchmarks/sim_throughput.py --device cpu --n 16 [--baseline 4] [--level 1]

The baseline simulates ``--baseline`` of the clips one at a time (default: all N)
and scales to N. Writes benchmarks/results/sim_throughput-<device>-n<N>-L<level>.json
with the command that made it. Kernels are compiled (or loaded) before timing.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

from clothgap import seeding
from sim import classes
from sim.materials import load_material
from sim.mesh import square_cloth
from sim.motions import wind_scene
from sim.solver import resolve_device
from sim.stage import simulate_scenes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--n", type=int, default=16, help="clips in the batch")
    ap.add_argument("--baseline", type=int, default=0, help="clips simulated one at a time (0 = all n)")
    ap.add_argument("--level", type=int, default=1, choices=(1, 2, 3))
    ap.add_argument("--grid", type=int, default=16)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--substeps", type=int, default=8)
    ap.add_argument("--out", type=Path, help="JSON path (default: benchmarks/results/sim_throughput-<device>-n<N>-L<level>.json)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    basis = load_material("camel-ponte-roma")
    mesh = square_cloth(0.5, args.grid, args.level)
    scenes = []
    for i in range(args.n):
        p, k = classes.jitter_class(i % classes.NUM_CLASSES, 0.1, seeding.rng(0, i, seeding.SIM, "material"))
        scenes.append(wind_scene(mesh, 0.5, basis.scaled(p, k), seeding.rng(0, i, seeding.SIM, "motion-wind")))
    kw = dict(fps=25.0, frames=args.frames, substeps=args.substeps, settle_s=0.4, device=device)
    simulate_scenes(scenes[:1], **{**kw, "frames": 1, "settle_s": 0.0})      # compile / load kernels

    t = time.perf_counter()
    simulate_scenes(scenes, **kw)
    batched = time.perf_counter() - t
    nb = args.baseline or args.n
    t = time.perf_counter()
    for s in scenes[:nb]:
        simulate_scenes([s], **kw)
    single = (time.perf_counter() - t) * args.n / nb

    steps = int(round(0.4 * 25 * args.substeps)) + args.frames * args.substeps
    vsteps = args.n * mesh.num_vertices * steps
    result = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "device": device, "platform": platform.platform(), "n": args.n, "level": args.level,
        "vertices_per_cloth": mesh.num_vertices, "steps_per_clip": steps,
        "batched": {"seconds": batched, "sequences_per_s": args.n / batched, "vertex_steps_per_s": vsteps / batched},
        "one_at_a_time": {"seconds": single, "clips_timed": nb, "sequences_per_s": args.n / single,
                          "vertex_steps_per_s": vsteps / single},
        "speedup": single / batched,
    }
    out = args.out or (Path(__file__).resolve().parent / "results"
                       / f"sim_throughput-{device.replace(':', '')}-n{args.n}-L{args.level}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
