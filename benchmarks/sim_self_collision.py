"""What self-collision costs and what it changes, per setting: the same clips simulated with it off and on.

    python benchmarks/sim_self_collision.py --device cuda                       # paper preset, wind-uniform1, 2,592 clips x 40 frames
    python benchmarks/sim_self_collision.py --device cuda --settings wind-uniform1,wind-uniform2,wind-uniform3,wind-adaptive
    python benchmarks/sim_self_collision.py --device cpu --n 4 --classes 0,1,9,10 --wind-nuisance full --every 1 \\
        --settings wind-uniform1,wind-uniform2,wind-uniform3,wind-adaptive    # the CPU rows of docs/simulation.md

The clips are the ``--preset``'s (default ``paper``: wind speed the only nuisance,
40 frames, 8 substeps, batches of ``sim.batch_size`` unless ``--batch``), clip
indices 0..n-1 of seed 0 over ``--classes`` (default all 54), built and
simulated by the sim stage's own functions (``sim.stage.build_scene``,
``simulate_scenes`` / ``simulate_adaptive_scenes``), each setting once with
self-collision off and once on (``--thickness``). Kernels are compiled (or
loaded) on one clip of each mode first, so the timings are simulation only.

Per setting and mode: seconds, clips per second, failed clips, the pairs
self-collision dropped unresolved (beyond a vertex's or edge's slots), and the intersecting triangle
pairs (``sim.intersections``) in the last frame of each clip (and, with
``--every K``, the most in any K-th frame): clips with any, total, max.
Counting runs on the host after the timing.

Writes ``benchmarks/results/sim_self_collision-<device>-n<N>.json`` (``--out``),
rewritten after each setting, with the command that made it.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from clothgap.config import PRESETS
from sim.intersections import count_intersections
from sim.solver import resolve_device
from sim.stage import build_scene, parse_setting, setting_simulator


def clip_counts(result, faces: np.ndarray | None, every: int) -> tuple[int, int]:
    """(intersecting pairs in the last frame, the most in any ``every``-th frame or the last)."""
    if result.frames is not None:
        frames = [(x, f) for x, f, _ in result.frames]
    else:
        frames = [(x, faces) for x in result.positions]
    picked = frames[::every] + [frames[-1]] if every else [frames[-1]]
    counts = [count_intersections(x, f) for x, f in picked]
    return counts[-1], max(counts)


def run_setting(cfg, name: str, n: int, batch: int, every: int, thickness: float, device: str) -> dict:
    setting = parse_setting(name)
    mesh, simulate = setting_simulator(cfg, setting)
    scenes = [build_scene(cfg, 0, i, setting, mesh)[0] for i in range(n)]
    kw = dict(fps=cfg.fps, frames=cfg.frames, substeps=cfg.substeps, settle_s=cfg.settle_s,
              cg_iterations=cfg.cg_iterations, cg_tolerance=cfg.cg_tolerance, collision_thickness=thickness,
              device=device)
    out = {"setting": name, "clips": n, "batch": batch, "vertices_per_cloth": mesh.num_vertices}
    for on in (False, True):
        simulate(scenes[:1], **{**kw, "frames": 1, "settle_s": 0.0}, self_collision=on)   # compile / load
        start = time.perf_counter()
        results = []
        for b in range(0, n, batch):
            results += simulate(scenes[b:b + batch], **kw, self_collision=on)
        seconds = time.perf_counter() - start
        ok = [r for r in results if r.reason is None]
        with ThreadPoolExecutor(max_workers=8) as pool:
            counts = list(pool.map(lambda r: clip_counts(r, mesh.faces, every), ok))
        last = [c[0] for c in counts]
        most = [c[1] for c in counts]
        row = {"seconds": round(seconds, 3), "clips_per_s": round(n / seconds, 3),
               "failed": len(results) - len(ok),
               "intersections_last_frame": {"clips_with_any": sum(c > 0 for c in last), "total": int(sum(last)),
                                            "max": int(max(last, default=0))}}
        if every:
            row[f"intersections_every_{every}_frames"] = {"clips_with_any": sum(c > 0 for c in most),
                                                         "max": int(max(most, default=0))}
        if on:
            row["pairs_unresolved"] = int(sum(r.collision_dropped or 0 for r in results))
        out["on" if on else "off"] = row
        print(f"{name} self-collision {'on ' if on else 'off'}: {seconds:8.2f} s, {json.dumps(row)}", flush=True)
    out["cost_ratio_on_off"] = round(out["on"]["seconds"] / out["off"]["seconds"], 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    ap.add_argument("--settings", default="wind-uniform1", help="comma-separated, e.g. wind-uniform1,arm-adaptive")
    ap.add_argument("--n", type=int, default=2592, help="clips per setting (clip indices 0..n-1)")
    ap.add_argument("--classes", default="", help="comma-separated class indices (default: all 54)")
    ap.add_argument("--frames", type=int, default=0, help="frames per clip (default: the preset's)")
    ap.add_argument("--batch", type=int, default=0, help="cloths per solver (default: the preset's sim.batch_size)")
    ap.add_argument("--thickness", type=float, default=0.0, help="m (default: the preset's sim.collision_thickness)")
    ap.add_argument("--wind-nuisance", default="", help="full or speed (default: the preset's sim.wind_nuisance)")
    ap.add_argument("--every", type=int, default=0, help="also count intersections in every K-th frame")
    ap.add_argument("--out", type=Path, help="JSON path (default: benchmarks/results/sim_self_collision-<device>-n<N>.json)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    cfg = PRESETS[args.preset]().sim
    classes = tuple(int(c) for c in args.classes.split(",") if c) or cfg.classes
    cfg = replace(cfg, classes=classes, frames=args.frames or cfg.frames, device=device,
                  wind_nuisance=args.wind_nuisance or cfg.wind_nuisance)
    batch = args.batch or cfg.batch_size
    thickness = args.thickness or cfg.collision_thickness
    result = {"command": " ".join([Path(sys.executable).name, *sys.argv]), "device": device,
              "platform": platform.platform(), "preset": args.preset, "frames": cfg.frames, "fps": cfg.fps,
              "substeps": cfg.substeps, "wind_nuisance": cfg.wind_nuisance, "classes": list(cfg.class_indices()),
              "thickness_m": thickness, "settings": []}
    out = args.out or (Path(__file__).resolve().parent / "results"
                       / f"sim_self_collision-{device.replace(':', '')}-n{args.n}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    for name in args.settings.split(","):
        result["settings"].append(run_setting(cfg, name, args.n, batch, args.every, thickness, device))
        out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
