"""Render throughput: one scene per clip updated in place (the stage's path) against one scene per frame.

Both loops run in the same process, on the same backend and the same synthetic
clips (a waving sheet, render.synthetic), at the same resolution and spp, and
write nothing to disk, so the ratio measures what in-place updates buy. The
baseline builds a fresh scene (``mi.load_dict``) for every frame, the way a
naive loop over mesh files would. Host peak RSS and, on CUDA, GPU memory in use
(nvidia-smi) are recorded. Writes a JSON under benchmarks/results/ with the
command line.

    python benchmarks/render_throughput.py                                  # auto backend, 224 px, 16 spp
    python benchmarks/render_throughput.py --backend scalar_rgb --resolution 32 --spp 2 --clips 4 --frames 10
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import shlex
import shutil
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from render.backend import BACKENDS, load_mitsuba
from render.scene import ClipRenderer
from render.synthetic import waving_sheet
from render.variants import get_variant

RESULTS = Path(__file__).resolve().parent / "results"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backend", default="auto", choices=BACKENDS)
    p.add_argument("--variant", default="paper")
    p.add_argument("--resolution", type=int, default=224)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--clips", type=int, default=8)
    p.add_argument("--frames", type=int, default=20, help="frames per clip")
    p.add_argument("--vertices", type=int, default=65, help="sheet vertices per side")
    p.add_argument("--warmup-clips", type=int, default=1, help="untimed clips first (kernel compilation)")
    p.add_argument("--out", type=Path, help="JSON path (default: benchmarks/results/render_throughput-<backend>-<time>.json)")
    return p.parse_args(argv)


def gpu_memory_mib() -> float | None:
    if shutil.which("nvidia-smi") is None:
        return None
    out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                         capture_output=True, text=True, check=False).stdout.split()
    return float(out[0]) if out else None


def host_peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def per_clip_loop(args, clips, variant) -> float:
    """The stage's path: one scene per clip, vertices updated in place each frame. Returns seconds."""
    start = time.perf_counter()
    for index, clip in enumerate(clips):
        renderer = ClipRenderer(clip, variant, resolution=args.resolution, spp=args.spp, run_seed=0,
                                clip_index=index, backend=args.backend)
        for t in range(clip.num_frames):
            renderer.render_frame(t)
    return time.perf_counter() - start


def per_frame_loop(args, clips, variant) -> float:
    """The baseline: a new scene for every frame (build, render one frame, drop). Returns seconds."""
    start = time.perf_counter()
    for index, clip in enumerate(clips):
        for t in range(clip.num_frames):
            renderer = ClipRenderer(clip, variant, resolution=args.resolution, spp=args.spp, run_seed=0,
                                    clip_index=index, backend=args.backend)
            renderer.render_frame(t)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    mi = load_mitsuba(args.backend)
    variant = get_variant(args.variant)
    clips = [waving_sheet(frames=args.frames, n=args.vertices, index=i) for i in range(args.clips)]
    warm = [waving_sheet(frames=2, n=args.vertices, index=1000 + i) for i in range(args.warmup_clips)]
    per_clip_loop(args, warm, variant)
    gpu_before = gpu_memory_mib()
    frames = args.clips * args.frames
    results = {}
    for name, loop in (("scene_per_clip_in_place", per_clip_loop), ("scene_per_frame_baseline", per_frame_loop)):
        seconds = loop(args, clips, variant)
        results[name] = {"seconds": round(seconds, 3), "frames_per_s": round(frames / seconds, 2),
                         "ms_per_frame": round(1000 * seconds / frames, 2),
                         "host_peak_rss_mib": round(host_peak_mib(), 1), "gpu_memory_used_mib": gpu_memory_mib()}
    report = {
        "command": shlex.join([sys.executable, *sys.argv]),
        "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": platform.node(), "backend": mi.variant(), "mitsuba": mi.__version__,
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "frames": frames, "gpu_memory_before_mib": gpu_before, **results,
        "speedup": round(results["scene_per_frame_baseline"]["seconds"]
                         / results["scene_per_clip_in_place"]["seconds"], 2),
    }
    out = args.out or RESULTS / f"render_throughput-{mi.variant()}-{datetime.now(timezone.utc):%Y%m%dT%H%M%S}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
