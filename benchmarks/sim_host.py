"""How much of a batch's simulation is the host's: Warp launches against everything else, per setting.

    python benchmarks/sim_host.py [--settings wind-uniform1,wind-adaptive] [--clips 16] [--frames 10]
                                  [--host-workers 0,4]

Simulates ``--clips`` ``paper``-preset clips (every 7th index) of each setting on the CPU under cProfile, as
the stage's batch simulator does (adaptive settings remesh every cloth after every frame). Reports the
seconds in Warp kernel launches (on a GPU these shrink) and on the host (these stay), the host's seconds
per clip-frame, and the host functions that take the most. ``--host-workers`` then times each adaptive setting
again without the profiler, remeshing in this process (0) and in pools of the given sizes
(``sim.adaptive.simulate_adaptive``), checks that the clips are the same bytes, and gives the wall seconds, their
ratio to 0 and the seconds of each phase (settle, steps, health, remesh, rebuild). Writes
benchmarks/results/sim_host-cpu-n<clips>.json with the command.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, paper_scenes, paper_sim_cpu, simulate_options, write_result  # noqa: E402  (benchmarks/common.py)


def profile_setting(name: str, clips: int, frames: int) -> dict:
    cfg, simulate, built = paper_scenes(name, range(0, 7 * clips, 7))
    scenes = [scene for scene, _ in built]
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.enable()
    results = simulate(scenes, **simulate_options(cfg, frames))
    profiler.disable()
    total = time.perf_counter() - start
    stats = pstats.Stats(profiler).stats
    launches = sum(v[3] for (path, _, func), v in stats.items() if func == "invoke" and "warp" in path)
    own = sorted(((v[2], f"{Path(path).name}:{line}({func})") for (path, line, func), v in stats.items()
                  if "/sim/" in path), reverse=True)[:8]
    host = total - launches
    return {"setting": name, "seconds": round(total, 2), "warp_launches_s": round(launches, 2),
            "host_s": round(host, 2), "host_ms_per_clip_frame": round(1000 * host / (clips * frames), 1),
            "failed": sum(r.reason is not None for r in results),
            "top_project_functions_own_s": [{"function": f, "seconds": round(t, 2)} for t, f in own]}


def clip_digest(results) -> str:
    """One hash of every adaptive clip's frames (positions, faces, uv), outcome and CG statistics."""
    h = hashlib.sha256()
    for r in results:
        h.update(repr((r.reason, r.cg, r.collision_dropped)).encode())
        for frame in r.frames or []:
            for a in frame:
                h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def time_host_workers(name: str, clips: int, frames: int, workers: list[int]) -> dict:
    """Wall seconds of an adaptive batch remeshed by ``workers`` processes each (0: this process)."""
    cfg, simulate, built = paper_scenes(name, range(0, 7 * clips, 7))
    scenes = [scene for scene, _ in built]
    out = {"setting": name, "runs": []}
    for w in workers:
        phases: dict[str, float] = {}
        start = time.perf_counter()
        results = simulate(scenes, **simulate_options(cfg, frames, host_workers=w, phases=phases))
        out["runs"].append({"host_workers": w, "seconds": round(time.perf_counter() - start, 2),
                            "phases_s": {k: round(v, 2) for k, v in phases.items()},
                            "clips_digest": clip_digest(results)})
    base = out["runs"][0]
    for run in out["runs"]:
        run["speedup"] = round(base["seconds"] / run["seconds"], 2)
        run["same_bytes_as_first"] = run["clips_digest"] == base["clips_digest"]
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--settings", default="wind-uniform1,wind-adaptive")
    ap.add_argument("--clips", type=int, default=16)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--host-workers", default="", help="comma-separated pool sizes to time adaptive settings with")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for name in args.settings.split(","):
        rows.append(profile_setting(name, args.clips, args.frames))
        print(json.dumps(rows[-1]), flush=True)
    pools = []
    if args.host_workers:
        workers = [0] + [int(w) for w in args.host_workers.split(",") if int(w) != 0]
        for name in args.settings.split(","):
            if name.endswith("adaptive"):
                pools.append(time_host_workers(name, args.clips, args.frames, workers))
                print(json.dumps(pools[-1]), flush=True)
    result = {"clips": args.clips, "frames": args.frames, "self_collision": paper_sim_cpu().self_collision,
              "cpus": os.cpu_count(), "rows": rows, **({"host_workers": pools} if pools else {})}
    write_result("sim_host.py", argv, result, args.out or RESULTS / f"sim_host-cpu-n{args.clips}.json")

if __name__ == "__main__":
    main()
