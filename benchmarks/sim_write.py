"""Sim finishing: the host time a clip costs after its simulation (health count + clip.npz), per clip.

    python benchmarks/sim_write.py RUN_DIR [--setting wind-uniform1] [--clips 200] [--threads 8]

Reads finished clips of a run (their simulated positions, so the cloth is folded as a
real clip's is), then times, per clip, what ``sim.stage.write_clip`` does besides the
meta: the intersection count of the last frame (``sim.intersections``) and writing
``clip.npz`` compressed (``np.savez_compressed``, the old format) and uncompressed
(``np.savez``, today's), one thread and ``--threads`` threads. Writes
benchmarks/results/sim_write-<setting>-<N>.json with the command that made it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from sim.intersections import count_intersections


def _per_clip_ms(fn, items, threads: int) -> float:
    start = time.perf_counter()
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(fn, items))
    else:
        for item in items:
            fn(item)
    return round((time.perf_counter() - start) / len(items) * 1e3, 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--clips", type=int, default=200)
    ap.add_argument("--threads", type=int, default=8)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    folders = sorted(p.parent for p in (args.run / "sim" / args.setting).glob("*/DONE"))[:args.clips]
    if not folders:
        sys.exit(f"error: no finished clips under {args.run / 'sim' / args.setting}")
    clips = []
    for folder in folders:
        with np.load(folder / "clip.npz") as z:
            arrays = {k: z[k] for k in z.files}
        vo = arrays["vertex_offsets"]
        last = arrays["positions"][vo[-2]:vo[-1]]
        clips.append((arrays, last))
    tmp = Path(tempfile.mkdtemp(prefix="sim_write-"))

    def count(item):
        arrays, last = item
        return count_intersections(last, arrays["faces"])

    def writer(save):
        def write(indexed):
            i, (arrays, _) = indexed
            save(tmp / f"{i}.npz", **arrays)
        return write

    items = list(enumerate(clips))
    rows = {}
    for threads in sorted({1, args.threads}):
        rows[f"threads_{threads}"] = {
            "count_intersections_ms": _per_clip_ms(count, clips, threads),
            "savez_compressed_ms": _per_clip_ms(writer(np.savez_compressed), items, threads),
            "savez_ms": _per_clip_ms(writer(np.savez), items, threads),
        }
    sizes = {}
    for save, name in ((np.savez_compressed, "compressed"), (np.savez, "plain")):
        save(tmp / f"size-{name}.npz", **clips[0][0])
        sizes[name] = os.path.getsize(tmp / f"size-{name}.npz")
    result = {"command": "python " + " ".join(sys.argv), "platform": platform.platform(),
              "cpus": os.cpu_count(), "setting": args.setting, "clips": len(clips),
              "positions_shape_first": list(clips[0][0]["positions"].shape), "per_clip": rows,
              "bytes_first_clip": sizes,
              "write_speedup_plain_over_compressed": {
                  k: round(v["savez_compressed_ms"] / v["savez_ms"], 2) for k, v in rows.items()}}
    out = args.out or Path(__file__).parent / "results" / f"sim_write-{args.setting}-{len(clips)}.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
