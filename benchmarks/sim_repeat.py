"""Is a simulation the same bytes when it is run again, and when its batch is split? On a given device.

    python benchmarks/sim_repeat.py --device cuda --clips 256 [--setting wind-uniform1] [--frames 20]

Simulates ``--clips`` ``paper``-preset clips three times on ``--device``: as one batch, as the same batch
again, and as two batches of half the clips each (what two executor workers do). Reports for each repeat
how many clips are byte-identical to the first run and the largest vertex distance from it, per clip
(median, max) and at the last frame. On the CPU every count is every clip (tests/test_benchmarks_scaling.py
checks the split); on a GPU the solver accumulates forces with float atomic adds, whose order is not fixed,
which this measures. Writes benchmarks/results/sim_repeat-<device>-<setting>-n<clips>.json with the command.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS, paper_scenes, paper_sim_cpu, simulate_options, write_result  # noqa: E402


def positions(results) -> list[np.ndarray | None]:
    """Each clip's positions over its frames, (T, V, 3); None for a failed clip."""
    out = []
    for r in results:
        if r.reason is not None:
            out.append(None)
        elif r.frames is not None:       # adaptive: frames of varying vertex counts
            out.append(np.concatenate([f[0].ravel() for f in r.frames]))
        else:
            out.append(np.asarray(r.positions))
    return out


def compare(first: list, other: list) -> dict:
    same, dist, last = 0, [], []
    for a, b in zip(first, other):
        if a is None or b is None or a.shape != b.shape:
            continue
        same += a.tobytes() == b.tobytes()
        if a.ndim == 3:
            dist.append(float(np.linalg.norm(a - b, axis=-1).max()))
            last.append(float(np.linalg.norm(a[-1] - b[-1], axis=-1).max()))
        else:
            dist.append(float(np.abs(a - b).max()))
    return {"clips": len(first), "byte_identical": same,
            "max_distance_mm": {"median": round(1000 * float(np.median(dist)), 4) if dist else None,
                                "max": round(1000 * max(dist), 4) if dist else None},
            "last_frame_max_distance_mm": round(1000 * max(last), 4) if last else None}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--clips", type=int, default=16)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    cfg, simulate, built = paper_scenes(args.setting, range(args.clips))
    scenes = [scene for scene, _ in built]
    opts = simulate_options(cfg, args.frames, args.device)
    first = positions(simulate(scenes, **opts))
    again = positions(simulate(scenes, **opts))
    half = len(scenes) // 2
    split = positions(simulate(scenes[:half], **opts)) + positions(simulate(scenes[half:], **opts))
    result = {"device": args.device, "setting": args.setting, "clips": args.clips, "frames": args.frames,
              "self_collision": paper_sim_cpu().self_collision,
              "failed": sum(p is None for p in first),
              "again": compare(first, again), "split_in_two_batches": compare(first, split)}
    print(json.dumps(result), flush=True)
    out = args.out or RESULTS / f"sim_repeat-{args.device}-{args.setting}-n{args.clips}.json"
    write_result("sim_repeat.py", argv, result, out)


if __name__ == "__main__":
    main()
