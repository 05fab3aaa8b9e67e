"""A training set's frames onto the GPU: the whole set gathered on the host and copied (how a training started
before ``learn.windows.gather_rows``) against gathered and copied chunk by chunk through two pinned buffers.

    python benchmarks/train_upload.py [--clips 20736] [--train-clips 15228] [--frames 40] [--size 112]
                                      [--device auto] [--repeats 2] [--workdir /tmp] [--out FILE]

Writes a frame array of ``--clips`` clips x ``--frames`` frames at ``--size`` px through
``render.frames.FrameStore`` (the packed array the render writes and the frame cache indexes in place: at the
``paper`` preset's 384 sequences a class, 20,736 clips, ~31 GB), then, each in a fresh process (its own CUDA
context), gathers the rows of ``--train-clips`` clips drawn at random (a split's training clips: 15,228 at 384 a
class) onto the device both ways, ``--repeats`` times, the two ways in alternating order. Reports each way's
seconds and its peak anonymous host memory over the process's own before the gather (RssAnon sampled every 5
ms: the frame array's page-cache pages are shared file pages, not counted) and, on CUDA, the pinned allocator's
peak; checks 64 random rows of each result against the array; the page cache holds the array, as after a render
on the same machine. Writes benchmarks/results/train_upload-<device>-n<clips>.json with the command. The array
is removed.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, either_first, frame_set_arguments, write_result  # noqa: E402  (benchmarks/common.py)
from render.frames import FrameStore, store_path  # noqa: E402

WAYS = ("whole", "chunked")


def _rss_anon_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def child(way: str, array: Path, rows_file: Path, device: str) -> dict:
    """One way, in this process: seconds and peak anonymous host memory; the rows checked."""
    import torch

    from learn.windows import UPLOAD_CHUNK_BYTES, gather_rows

    frames = np.load(array, mmap_mode="r")
    rows = np.load(rows_file)
    if device == "cuda":
        torch.zeros(1, device=device)          # the CUDA context before the baseline
    base = peak = _rss_anon_mib()
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.is_set():
            peak = max(peak, _rss_anon_mib())
            time.sleep(0.005)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    started = time.perf_counter()
    host = None
    if way == "whole":       # the host copy lives until the set is on the device, as it did in WindowSet
        host = torch.from_numpy(np.ascontiguousarray(frames[rows]))
        out = host.to(device)
    else:
        out = gather_rows(frames, rows, device, chunk_bytes=UPLOAD_CHUNK_BYTES)   # (on a CPU too: its chunks)
    if device == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - started
    done.set()
    sampler.join()
    peak = max(peak, _rss_anon_mib())      # (one numpy gather may hold the interpreter's lock past the samples)
    del host
    pinned = None
    if device == "cuda":      # pinned buffers come from the driver and may not show in RssAnon
        stats = torch.cuda.host_memory_stats()
        peak_bytes = stats.get("allocated_bytes.peak", stats.get("allocated_bytes.all.peak"))
        pinned = None if peak_bytes is None else round(peak_bytes / 2**20, 1)
    check = np.random.default_rng(0).choice(len(rows), size=min(64, len(rows)), replace=False)
    same = all(np.array_equal(out[i].cpu().numpy(), frames[rows[i]]) for i in check)
    return {"way": way, "seconds": round(seconds, 6), "gib_per_s": round(out.numel() / seconds / 2**30, 2),
            "peak_anon_host_mib_over_start": round(peak - base, 1), "peak_pinned_host_mib": pinned,
            "rows_checked_equal": bool(same)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    frame_set_arguments(ap, clips=20736)
    ap.add_argument("--train-clips", type=int, default=15228)
    ap.add_argument("--device", default="auto", help="cuda, cpu, or auto (cuda when there is one)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--child", nargs=3, metavar=("WAY", "ARRAY", "ROWS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    device = args.device
    if device == "auto":
        import torch
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.child:
        print(json.dumps(child(args.child[0], Path(args.child[1]), Path(args.child[2]), device)))
        return
    if not 0 < args.train_clips <= args.clips:
        raise SystemExit(f"--train-clips must be in 1..--clips ({args.clips}), not {args.train_clips}")
    work = Path(tempfile.mkdtemp(prefix="train_upload-", dir=args.workdir))
    try:
        rows_file = work / "rows.npy"
        started = time.perf_counter()       # written as the render writes a setting's packed frames
        store = FrameStore(store_path(work, args.size), args.clips, args.frames, args.size)
        array, shape = store.path, store.shape
        block = np.random.default_rng(1).integers(0, 256, (args.frames, args.size, args.size, 3), dtype=np.uint8)
        for c in range(args.clips):                # each clip a random block shifted by its index: rows differ
            store.write(c, block + np.uint8(c % 251))
        write_seconds = time.perf_counter() - started
        clips = np.sort(np.random.default_rng(2).choice(args.clips, size=args.train_clips, replace=False))
        rows = (clips[:, None] * args.frames + np.arange(args.frames)).ravel()
        np.save(rows_file, rows)
        runs = []
        for way in either_first(WAYS, args.repeats):
            r = subprocess.run([sys.executable, __file__, "--device", device, "--child", way, str(array),
                                str(rows_file)], capture_output=True, text=True, check=True)
            runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
            print(runs[-1], flush=True)
    finally:
        shutil.rmtree(work)
    summary = {}
    for way in WAYS:
        mine = [r for r in runs if r["way"] == way]
        summary[way] = {"median_seconds": round(statistics.median(r["seconds"] for r in mine), 6),
                        "max_peak_anon_host_mib_over_start": max(r["peak_anon_host_mib_over_start"] for r in mine),
                        "rows_checked_equal": all(r["rows_checked_equal"] for r in mine)}
    gib = args.train_clips * args.frames * args.size * args.size * 3 / 2**30
    result = {"device": device, "host": platform.node(), "set_gib": round(gib, 2),
              "array_gib": round(np.prod(shape) / 2**30, 2), "array_write_seconds": round(write_seconds, 1),
              "runs": runs, "summary": summary,
              "chunked_over_whole_seconds": round(summary["chunked"]["median_seconds"]
                                                  / summary["whole"]["median_seconds"], 3)}
    out = args.out or RESULTS / f"train_upload-{device}-n{args.clips}.json"
    write_result("train_upload.py", argv, result, out)


if __name__ == "__main__":
    main()
