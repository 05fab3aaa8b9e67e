"""Render throughput: one frame per Mitsuba launch (the baseline) against K frames per launch (render.batch).

All loops run in one process, on the same backend, on the same synthetic clips
(waving sheets, render.synthetic, ``--vertices`` per side) at the same
resolution, for each spp in ``--spp``:

* ``one_frame_per_launch``: the stage's one-scene-per-clip path, the cloth
  moved in place, one ``mi.render`` per frame (ClipRenderer.render_hdr);
* ``batched_k<K>``: K frames of a clip per launch (BatchRenderer), for each K
  in ``--k``;
* with ``--write``, the same again through the stage's ``render_clip`` (tone
  mapping, EXR + PNG on a writer pool) into a temporary folder, so IO
  overlapping rendering is measured too.

Every timed frame is copied to the host. Host RSS and (with nvidia-smi) GPU
memory are sampled every ``--sample-s`` seconds over each loop, so a leak shows
as a slope (``memory``: first, last, max). Batched frames are equal in
expectation but noisier at equal spp (next-event estimation is spread over
every slot's lights), so ``noise`` gives each path's RMS error against a
high-spp reference frame and ``equal_noise_frames_per_s`` rescales each rate by
(RMS / baseline RMS)^2, the spp factor it would need to be as clean. Writes a
JSON under benchmarks/results/ with the command line.

    python benchmarks/render_throughput.py --device cuda                          # 224 px, 16 and 4 spp, 2,000 frames
    python benchmarks/render_throughput.py --device cpu --resolution 32 --spp 4 --clips 4 --frames 8 --k 4
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from render.backend import BACKENDS, find_libllvm, load_mitsuba  # noqa: E402
from render.batch import BatchRenderer  # noqa: E402
from render.config import RenderConfig  # noqa: E402
from render.scene import ClipRenderer  # noqa: E402
from render.synthetic import waving_sheet  # noqa: E402
from render.variants import get_variant  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=("cuda", "cpu"), help="cuda: cuda_ad_rgb; cpu: llvm_ad_rgb (scalar_rgb "
                   "without a good libLLVM); overrides --backend")
    p.add_argument("--backend", default="auto", choices=BACKENDS)
    p.add_argument("--variant", default="paper")
    p.add_argument("--resolution", type=int, default=224)
    p.add_argument("--spp", default="16,4", help="comma-separated samples per pixel, one round each")
    p.add_argument("--k", default="4,8,16", help="comma-separated frames per launch for the batched path")
    p.add_argument("--clips", type=int, default=50)
    p.add_argument("--frames", type=int, default=40, help="frames per clip")
    p.add_argument("--vertices", type=int, default=65, help="sheet vertices per side")
    p.add_argument("--write", action="store_true", help="also time the stage's render_clip (EXR + PNG, writer pool)")
    p.add_argument("--writer-threads", type=int, default=4)
    p.add_argument("--reference-spp", type=int, default=0, help="spp of the noise reference (default 16 x spp)")
    p.add_argument("--sample-s", type=float, default=0.5, help="memory sampling period")
    p.add_argument("--out", type=Path, help="JSON path (default: benchmarks/results/render_batch-<backend>-<time>.json)")
    args = p.parse_args(argv)
    if args.device == "cuda":
        args.backend = "cuda_ad_rgb"
    elif args.device == "cpu":
        args.backend = "llvm_ad_rgb" if find_libllvm() else "scalar_rgb"
    args.spp = [int(s) for s in str(args.spp).split(",")]
    args.k = [int(k) for k in str(args.k).split(",")]
    return args


def gpu_memory_mib() -> float | None:
    if shutil.which("nvidia-smi") is None:
        return None
    out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                         capture_output=True, text=True, check=False).stdout.split()
    return float(out[0]) if out else None


def host_rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


class MemorySampler:
    """Samples host RSS and GPU memory in a thread while a loop runs."""

    def __init__(self, period: float):
        self.period, self.samples, self._stop = period, [], threading.Event()

    def __enter__(self):
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while True:
            self.samples.append((host_rss_mib(), gpu_memory_mib()))
            if self._stop.wait(self.period):
                break

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.samples.append((host_rss_mib(), gpu_memory_mib()))

    def summary(self) -> dict:
        out = {"samples": len(self.samples)}
        for i, name in enumerate(("host_rss_mib", "gpu_used_mib")):
            values = [s[i] for s in self.samples if s[i] is not None]
            if values:
                out[name] = {"first": round(values[0], 1), "last": round(values[-1], 1), "max": round(max(values), 1)}
        return out


def make_renderer(args, clip, index: int, spp: int) -> ClipRenderer:
    return ClipRenderer(clip, get_variant(args.variant), resolution=args.resolution, spp=spp, run_seed=0,
                        clip_index=index, backend=args.backend)


def render_loop(args, clips, spp: int, k: int) -> int:
    """Render every frame of every clip to host memory, k frames per launch (1: the baseline). Returns frames."""
    frames = 0
    for index, clip in enumerate(clips):
        r = make_renderer(args, clip, index, spp)
        if k == 1:
            for t in range(clip.num_frames):
                r.render_hdr(t)
                frames += 1
        else:
            for _ in BatchRenderer(r, k).hdr_frames():
                frames += 1
    return frames


def stage_loop(args, clips, spp: int, k: int) -> int:
    """The stage's render_clip (tone mapping, EXR + PNG through a shared writer pool) into a temporary folder."""
    from render.stage import render_clip

    config = RenderConfig(variants=(args.variant,), resolution=args.resolution, spp=spp, backend=args.backend,
                          frames_per_launch=k, writer_threads=args.writer_threads)
    frames = 0
    with tempfile.TemporaryDirectory(prefix="render-bench-") as tmp, \
            ThreadPoolExecutor(args.writer_threads) as writer:
        for index, clip in enumerate(clips):
            meta = render_clip(clip, get_variant(args.variant), Path(tmp) / f"c{index:05d}", config=config,
                               run_seed=0, clip_index=index, writer=writer)
            frames += meta["num_frames"]
    return frames


def noise(args, clip, spp: int, ks: list[int]) -> dict:
    """RMS error of frame 0 against a high-spp one-frame render, for the baseline and each K."""
    ref_spp = args.reference_spp or 16 * spp
    reference = make_renderer(args, clip, 0, ref_spp).render_hdr(0)[..., :3]
    out = {"reference_spp": ref_spp}
    for k in [1, *ks]:
        r = make_renderer(args, clip, 0, spp)
        frame = r.render_hdr(0) if k == 1 else BatchRenderer(r, k).render_hdr(list(range(min(k, clip.num_frames))))[0]
        out["one_frame_per_launch" if k == 1 else f"batched_k{k}"] = float(np.sqrt(np.mean((frame[..., :3] - reference) ** 2)))
    return out


def _stage_importable(result: dict) -> bool:
    """render.stage needs PyAV (video compression) and PIL; a machine without them skips --write, saying why."""
    try:
        import render.stage  # noqa: F401
    except ImportError as e:
        result["with_output"] = {"skipped": f"render.stage does not import here: {e}"}
        return False
    return True


def timed(loop, args, clips, spp: int, k: int) -> dict:
    with MemorySampler(args.sample_s) as memory:
        start = time.perf_counter()
        frames = loop(args, clips, spp, k)
        seconds = time.perf_counter() - start
    return {"frames": frames, "seconds": round(seconds, 3), "frames_per_s": round(frames / seconds, 2),
            "ms_per_frame": round(1000 * seconds / frames, 3), "memory": memory.summary()}


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    mi = load_mitsuba(args.backend)
    clips = [waving_sheet(frames=args.frames, n=args.vertices, index=i) for i in range(args.clips)]
    warm = [waving_sheet(frames=max(args.k), n=args.vertices, index=1000)]
    rounds = []
    for spp in args.spp:
        for k in [1, *args.k]:  # untimed: compile (and cache) every kernel first
            render_loop(args, warm, spp, k)
        result: dict = {"spp": spp, "samples_per_frame": args.resolution ** 2 * spp, "render_only": {}}
        for k in [1, *args.k]:
            name = "one_frame_per_launch" if k == 1 else f"batched_k{k}"
            result["render_only"][name] = timed(render_loop, args, clips, spp, k)
        base = result["render_only"]["one_frame_per_launch"]["frames_per_s"]
        result["noise_rms"] = noise(args, clips[0], spp, args.k)
        base_rms = result["noise_rms"]["one_frame_per_launch"]
        for name, row in result["render_only"].items():
            row["speedup"] = round(row["frames_per_s"] / base, 3)
            row["samples_per_s_M"] = round(row["frames_per_s"] * result["samples_per_frame"] / 1e6, 1)
            ratio = result["noise_rms"][name] / base_rms
            row["noise_rms_ratio"] = round(ratio, 3)
            row["equal_noise_frames_per_s"] = round(row["frames_per_s"] / ratio ** 2, 2)
        if args.write and _stage_importable(result):
            best = max(args.k, key=lambda k: result["render_only"][f"batched_k{k}"]["frames_per_s"])
            result["with_output"] = {name: timed(stage_loop, args, clips, spp, k)
                                     for name, k in (("one_frame_per_launch", 1), (f"batched_k{best}", best))}
        rounds.append(result)
        print(json.dumps(result, indent=2), flush=True)
    report = {
        "command": shlex.join([sys.executable, *sys.argv]) if argv is None else shlex.join(argv),
        "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": platform.node(), "backend": mi.variant(), "mitsuba": mi.__version__,
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "gpu_memory_before_mib": gpu_memory_mib(), "rounds": rounds,
    }
    out = args.out or RESULTS / f"render_batch-{mi.variant()}-{datetime.now(timezone.utc):%Y%m%dT%H%M%S}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
