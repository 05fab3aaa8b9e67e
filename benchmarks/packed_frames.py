"""A setting's frames per clip (``frames.npy`` each, then the frame cache copies them) against packed at render time
(``render.pack_frames``: one array a setting, which the frame cache indexes in place): disk used and seconds.

    python benchmarks/packed_frames.py [--clips 2592] [--frames 40] [--size 112] [--workdir /tmp] [--out FILE]

Writes ``--clips`` clips of random frames in the run layout both ways, as the render stage writes them (each
clip's frames, its ``meta.json``, its ``DONE``; no Mitsuba: the frames are what is stored, not how they are
rendered), then builds each run's frame cache at the render resolution (``learn.dataset.build_cache``, one
process) and checks that both caches hold the same bytes for every clip. Reports, for each layout, the seconds
to write the clips, the seconds to build the cache, and the disk the frames take (allocated blocks of the render
and cache folders), and the ratios of per-clip to packed. The page cache holds the frames in both (as after a
render on the same machine). Writes benchmarks/results/packed_frames-<host>-n<clips>.json with the command; the
stand-in folders are removed.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, frame_set_arguments, write_result  # noqa: E402  (benchmarks/common.py)
from clothgap.config import preset  # noqa: E402
from clothgap.runs import Run, atomic_write_json, clip_id, mark_done  # noqa: E402
from learn.dataset import build_cache  # noqa: E402
from render.frames import STORE_KEY, FrameStore, store_path, write_frames  # noqa: E402

SETTING, VARIANT = "wind-uniform1", "paper"


def allocated_bytes(*folders: Path) -> int:
    """Disk blocks in use under ``folders`` (a sparse file counts what it holds, not its length)."""
    return sum(p.stat().st_blocks * 512 for folder in folders if folder.is_dir()
               for p in folder.rglob("*") if p.is_file())


def write_clips(run: Run, packed: bool, clips: int, frames: int, size: int) -> float:
    """The clips' frames, meta and DONE as the render stage leaves them; returns the seconds it took."""
    rng = np.random.default_rng(0)
    folder = run.render_dir(VARIANT, SETTING)
    start = time.perf_counter()
    store = FrameStore(store_path(folder, size), clips, frames, size, pending=clips) if packed else None
    for index in range(clips):
        clip = folder / clip_id(index)
        clip.mkdir(parents=True, exist_ok=True)
        pixels = rng.integers(0, 256, size=(frames, size, size, 3), dtype=np.uint8)
        meta = {"clip_id": clip.name, "class_index": index % 54, "num_frames": frames, "index": index}
        if store is not None:
            meta[STORE_KEY] = store.write(index, pixels)
        else:
            write_frames(clip, pixels)
        atomic_write_json(clip / "meta.json", meta)
        mark_done(clip)
    return round(time.perf_counter() - start, 3)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    frame_set_arguments(ap)
    args = ap.parse_args(argv)
    frame_bytes = args.clips * args.frames * args.size ** 2 * 3
    if shutil.disk_usage(args.workdir).free < 3.3 * frame_bytes:
        ap.error(f"{args.workdir} needs about {3.3 * frame_bytes / 2**30:.1f} GiB free (both layouts)")
    root = Path(tempfile.mkdtemp(prefix="packed_frames-", dir=args.workdir))
    result = {"clips": args.clips, "frames": args.frames, "size": args.size, "frame_bytes": frame_bytes,
              "host": platform.node(), "cpus": os.cpu_count()}
    try:
        caches = {}
        for layout in ("per_clip", "packed"):
            cfg = preset("paper")
            cfg = replace(cfg, sim=replace(cfg.sim, motions=("wind",), remeshing=("uniform1",),
                                           sequences_per_class=max(1, -(-args.clips // 54)), frames=args.frames),
                          render=replace(cfg.render, resolution=args.size, pack_frames=layout == "packed"),
                          train=replace(cfg.train, clip_len=min(cfg.train.clip_len, args.frames)))
            run = Run.create_or_resume(root / layout, cfg)
            write_s = write_clips(run, layout == "packed", args.clips, args.frames, args.size)
            t0 = time.perf_counter()
            caches[layout] = build_cache(run, VARIANT, SETTING, args.size, progress=False, processes=0)
            cache_s = round(time.perf_counter() - t0, 3)
            result[layout] = {"write_s": write_s, "cache_s": cache_s,
                              "disk_bytes": allocated_bytes(run.root / "render", run.root / "cache"),
                              "cache_array": str(caches[layout].array_path.relative_to(run.root))}
            print(layout, result[layout], flush=True)
        a, b = caches["per_clip"], caches["packed"]
        result["same_bytes"] = all(
            np.array_equal(a.frames[c.offset:c.offset + c.num_frames],
                           b.frames[b.clips[cid].offset:b.clips[cid].offset + c.num_frames])
            for cid, c in a.clips.items())
        per, packed = result["per_clip"], result["packed"]
        result["ratios"] = {
            "disk_per_clip_over_packed": round(per["disk_bytes"] / max(packed["disk_bytes"], 1), 2),
            "write_and_cache_s_per_clip_over_packed": round((per["write_s"] + per["cache_s"])
                                                            / max(packed["write_s"] + packed["cache_s"], 1e-9), 2)}
        print("ratios", result["ratios"], "same bytes", result["same_bytes"])
        if not result["same_bytes"]:
            raise SystemExit("the two layouts' caches differ: a bug, not a timing")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    out = args.out or RESULTS / f"packed_frames-{platform.node() or 'host'}-n{args.clips}.json"
    write_result("packed_frames.py", argv, result, out)


if __name__ == "__main__":
    main()
