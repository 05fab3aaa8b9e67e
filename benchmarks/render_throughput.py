"""Render throughput at one frame per Mitsuba launch, as a ratio to the path tracer's own ceiling.

All loops run on the same backend, on the same synthetic clips (waving sheets,
render.synthetic, ``--vertices`` per side, each clip its own texture, lights and
camera) at the same resolution, for each spp in ``--spp``; every timed frame is
copied to the host:

* ``ceiling``: the device time of Dr.Jit's kernels per frame (path tracing,
  normals, copies; read from its kernel history over a few pooled frames; OptiX
  BVH builds and all host work left out) and the frame rate that time allows,
  ``ceiling_frames_per_s``. Every row below gets ``ceiling_ratio``, its
  frames/s over that ceiling, measured in the same run;
* ``scene_per_clip``: a new Mitsuba scene for every clip, the cloth moved in
  place frame to frame (``reuse_scenes=False``; on CUDA each new scene costs an
  OptiX compile of the path tracer);
* ``pooled``: one scene per structure, retargeted to each clip in place
  (render.scene.ScenePool, the stage's default);
* ``pooled_frozen``: the same with ``mi.render`` under ``dr.freeze``; beside its
  rate, ``frozen_rel_error`` is its frames' mean relative difference from the
  plain frames at the same seeds (0 when replaying is exact on this backend);
* ``processes_<N>``: N processes sharing the device, each rendering its share of
  the clips pooled (frozen too with ``--procs-freeze``), timed from a barrier
  after every process has compiled;
* ``batched_k<K>`` (with ``--k``): K frames of a clip per launch (render.batch),
  with its noise against a high-spp reference (batched frames are noisier);
* ``phases``: host milliseconds per frame in each step of the stage's path
  (pooled, frozen where it can be) on four clips, for both ways of finishing a
  frame: ``host_finish`` (a new clip's setup, the geometry update, the render
  call, the float32 RGBA read-back where the host waits for the device,
  composite + tone map in numpy) and ``device_finish`` (the same, with the
  composite + tone map + sRGB8 kernel launched on the device, ``finish``, and
  the uint8 frame read back); ``device_over_host`` is the ratio of their
  per-frame totals, and ``device_vs_host`` how far the two paths' frames differ
  (the largest code difference and the share of values that differ: at most 1,
  rarely, on CUDA; 0 on llvm_ad_rgb).

With ``--write``, ``with_output`` times the stage's own ``render_clip`` (the
stage's scene pooling and freezing, frames finished on the device where the
backend can, ``frames.npy`` written per clip) for each output set of
``--outputs``: ``npy`` (the array alone, the ``paper`` preset), ``png`` (plus
PNGs), ``png+exr`` (plus EXRs: what every clip wrote before frames.npy); each
row records the files it wrote. ``<outputs>_host_finish`` is the same loop with
frames finished on the host (``render_clip(device_finish=False)``, the stage
before device finishing), and the device row's ``over_host_finish`` is its
frames/s over that row's. ``--write-procs`` runs the same in N processes at once, as
``clothgap render --executor process`` does. Host RSS and (with nvidia-smi) GPU
memory are sampled over each single-process loop, so a leak shows as a slope
(``memory``: first, last, max). Writes a JSON under benchmarks/results/ with the
command line.

    python benchmarks/render_throughput.py --device cuda --resolution 112 --spp 16 --write --write-procs 4
    python benchmarks/render_throughput.py --device cpu --resolution 32 --spp 4 --clips 4 --frames 8 --procs "" --write
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
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
    p.add_argument("--k", default="", help="comma-separated frames per launch for the batched path (render.batch)")
    p.add_argument("--procs", default="2,4", help="comma-separated process counts sharing the device")
    p.add_argument("--procs-freeze", action="store_true", help="processes render frozen too")
    p.add_argument("--no-freeze", action="store_true", help="skip the pooled_frozen loop")
    p.add_argument("--clips", type=int, default=50)
    p.add_argument("--frames", type=int, default=40, help="frames per clip")
    p.add_argument("--vertices", type=int, default=65, help="sheet vertices per side")
    p.add_argument("--write", action="store_true", help="also time the stage's render_clip for each of --outputs")
    p.add_argument("--outputs", default="npy,png+exr", help="comma-separated output sets for --write: npy, png, "
                   "png+exr (frames.npy is always written)")
    p.add_argument("--write-procs", default="", help="comma-separated process counts for the --write loops")
    p.add_argument("--ceiling-frames", type=int, default=8, help="frames whose kernel time gives the ceiling")
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
    args.k = [int(k) for k in str(args.k).split(",") if k]
    args.procs = [int(n) for n in str(args.procs).split(",") if n]
    args.write_procs = [int(n) for n in str(args.write_procs).split(",") if n]
    args.outputs = [o for o in str(args.outputs).split(",") if o]
    bad = [o for o in args.outputs if o not in OUTPUTS]
    if bad:
        p.error(f"--outputs: unknown output set(s) {', '.join(bad)}; known: {', '.join(OUTPUTS)}")
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


# How each single-process loop makes its renderers: (reuse_scenes, freeze).
MODES = {"scene_per_clip": (False, False), "pooled": (True, False), "pooled_frozen": (True, True)}
# What the --write loops write besides frames.npy: (render.write_png, render.write_hdr).
OUTPUTS = {"npy": (False, False), "png": (True, False), "png+exr": (True, True)}


def make_renderer(args, clip, index: int, spp: int, mode: str = "scene_per_clip") -> ClipRenderer:
    reuse, freeze = MODES[mode]
    return ClipRenderer(clip, get_variant(args.variant), resolution=args.resolution, spp=spp, run_seed=0,
                        clip_index=index, backend=args.backend, reuse_scenes=reuse, freeze=freeze)


def render_loop(args, clips, spp: int, k: int, mode: str = "scene_per_clip") -> int:
    """Render every frame of every clip to host memory, k frames per launch. Returns frames."""
    frames = 0
    for index, clip in enumerate(clips):
        r = make_renderer(args, clip, index, spp, mode if k == 1 else "scene_per_clip")
        if k == 1:
            for t in range(clip.num_frames):
                r.render_hdr(t)
                frames += 1
        else:
            for _ in BatchRenderer(r, k).hdr_frames():
                frames += 1
    return frames


def frozen_error(args, clips, spp: int) -> float:
    """Mean relative difference of frozen frames from plain ones (same clips, same seeds), over 3 clips."""
    errors = []
    for index, clip in enumerate(clips[:3]):
        plain = make_renderer(args, clip, index, spp, "pooled")
        frames = [plain.render_hdr(t) for t in range(clip.num_frames)]
        frozen = make_renderer(args, clip, index, spp, "pooled_frozen")
        for t, ref in enumerate(frames):
            errors.append(float(np.abs(frozen.render_hdr(t) - ref).mean() / max(np.abs(ref).mean(), 1e-12)))
    return float(np.mean(errors))


def _process_worker(args, spp: int, indices: list[int], freeze: bool, barrier, queue, outputs: str = "") -> None:
    mode = "pooled_frozen" if freeze else "pooled"
    warm = [waving_sheet(frames=args.frames, n=args.vertices, index=10_000 + indices[0])]
    clips = [waving_sheet(frames=args.frames, n=args.vertices, index=i) for i in indices]
    if outputs:
        stage_loop(args, warm, spp, 1, outputs)
    else:
        render_loop(args, warm, spp, 1, mode)
    barrier.wait()
    start = time.perf_counter()
    if outputs:
        frames = stage_loop(args, clips, spp, 1, outputs, indices)
    else:
        frames = 0
        for index, clip in zip(indices, clips):
            r = make_renderer(args, clip, index, spp, mode)
            for t in range(clip.num_frames):
                r.render_hdr(t)
                frames += 1
    queue.put((frames, start, time.perf_counter()))


def processes_loop(args, spp: int, n: int, outputs: str = "") -> dict:
    """N processes sharing the device, each rendering every N-th clip; aggregate rate from the barrier on.

    With ``outputs``, each process runs the stage's render_clip (``stage_loop``) instead of bare renders."""
    ctx = mp.get_context("spawn")
    barrier, queue = ctx.Barrier(n), ctx.Queue()
    shares = [list(range(args.clips))[i::n] for i in range(n)]
    workers = [ctx.Process(target=_process_worker, args=(args, spp, share, args.procs_freeze, barrier, queue, outputs))
               for share in shares if share]
    for w in workers:
        w.start()
    results = [queue.get() for _ in workers]
    for w in workers:
        w.join()
    frames = sum(r[0] for r in results)
    seconds = max(r[2] for r in results) - min(r[1] for r in results)
    return {"processes": len(workers), "frozen": args.procs_freeze if not outputs else "stage default",
            "frames": frames, "seconds": round(seconds, 3),
            "frames_per_s": round(frames / seconds, 2), "ms_per_frame": round(1000 * seconds / frames, 3),
            "gpu_used_mib_after": gpu_memory_mib()}


def stage_loop(args, clips, spp: int, k: int, outputs: str = "png+exr", indices: list[int] | None = None,
               written: dict | None = None, device_finish: bool = True, in_flight: int = 1,
               frames_out: dict | None = None) -> int:
    """The stage's render_clip (frames finished on the device unless ``device_finish`` is False, ``in_flight``
    frames launched before the oldest is read back, a shared writer pool, frames.npy, ``outputs``) into a
    temporary folder; ``written`` gets the number of files of each kind it wrote, ``frames_out`` each clip's
    frames.npy array."""
    from render.stage import render_clip

    write_png, write_hdr = OUTPUTS[outputs]
    config = RenderConfig(variants=(args.variant,), resolution=args.resolution, spp=spp, backend=args.backend,
                          frames_per_launch=k, writer_threads=args.writer_threads, write_png=write_png,
                          write_hdr=write_hdr, frames_in_flight=in_flight)
    frames = 0
    with tempfile.TemporaryDirectory(prefix="render-bench-") as tmp, \
            ThreadPoolExecutor(args.writer_threads) as writer:
        for index, clip in zip(indices or range(len(clips)), clips):
            meta = render_clip(clip, get_variant(args.variant), Path(tmp) / f"c{index:05d}", config=config,
                               run_seed=0, clip_index=index, writer=writer, device_finish=device_finish)
            frames += meta["num_frames"]
            if frames_out is not None:
                frames_out[index] = np.load(Path(tmp) / f"c{index:05d}" / "frames.npy")
        if written is not None:
            for kind in ("npy", "png", "exr"):
                written[kind] = sum(1 for _ in Path(tmp).rglob(f"*.{kind}"))
    return frames


def phases(args, clips, spp: int, mode: str, device: bool = False) -> dict:
    """Host milliseconds per frame in each step of the stage's one-frame path (no extra synchronisation, so a
    wait for the device shows where it happens): geometry update, render call, then either the float32 read-back
    and composite + tone map on the host, or (``device``) the finishing kernel's launch and the uint8 read-back."""
    steps = ("geometry", "render_call", "finish", "readback") if device else \
        ("geometry", "render_call", "readback", "finish")
    totals = dict.fromkeys(("clip_setup", *steps), 0.0)
    frames = 0
    for index, clip in enumerate(clips):
        t0 = time.perf_counter()
        r = make_renderer(args, clip, index, spp, mode)
        r.background                                    # the clip's background draw, on its helper thread
        finisher = r.device_finisher if device else None
        totals["clip_setup"] += time.perf_counter() - t0
        for t in range(clip.num_frames):
            t0 = time.perf_counter()
            r._set_geometry(t)
            t1 = time.perf_counter()
            image = r._render(spp, (r.sampler_seed + t) & 0xFFFFFFFF)
            t2 = time.perf_counter()
            if device:
                codes = finisher(image.array)
                t3 = time.perf_counter()
                finisher.to_host(codes)
            else:
                hdr = np.array(image, np.float32)
                t3 = time.perf_counter()
                r.finish(hdr, t)
            t4 = time.perf_counter()
            for key, dt in zip(steps, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                totals[key] += dt
            frames += 1
    return {"mode": mode, "frames": frames, **{f"ms_{k}": round(1e3 * v / frames, 3) for k, v in totals.items()},
            "ms_per_frame": round(1e3 * sum(totals.values()) / frames, 3)}


def device_vs_host(args, clips, spp: int, mode: str) -> dict:
    """How far frames finished on the device are from the host's finish of the same render (same scene, frame
    and seed): the largest code difference and the share of values that differ, over every frame of ``clips``."""
    largest, differing, values = 0, 0, 0
    for index, clip in enumerate(clips):
        r = make_renderer(args, clip, index, spp, mode)
        for t in range(clip.num_frames):
            host = r.finish(r.render_hdr(t), t).astype(np.int16)
            device, _ = r.render_finished(t)
            largest = max(largest, int(np.abs(device - host).max()))
            differing += int(np.count_nonzero(device != host))
            values += host.size
    return {"frames": sum(c.num_frames for c in clips), "max_code_difference": largest,
            "share_differing": differing / values}


def ceiling(args, clips, spp: int) -> dict:
    """Device time of Dr.Jit's kernels per frame on pooled scenes, and the frame rate it allows."""
    import drjit as dr

    frames = []
    for index, clip in enumerate(clips):
        frames += [(index, clip, t) for t in range(clip.num_frames)]
    frames = frames[:max(1, args.ceiling_frames)]
    renderers = {}
    dr.kernel_history()                 # clears it
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for index, clip, t in frames:
            if index not in renderers:
                renderers[index] = make_renderer(args, clip, index, spp, "pooled")
            renderers[index].render_hdr(t)
        history = dr.kernel_history()
    ms = sum(h.get("execution_time", 0.0) for h in history) / len(frames)
    jit = [h for h in history if h.get("type") == dr.KernelType.JIT]
    return {"frames": len(frames), "kernel_ms_per_frame": round(ms, 4),
            "launches_per_frame": round(len(history) / len(frames), 1),
            "largest_kernel_ms": round(max((h.get("execution_time", 0.0) for h in jit), default=0.0), 4),
            "ceiling_frames_per_s": round(1000.0 / ms, 1) if ms > 0 else None}


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


def timed(loop, args, clips, spp: int, k: int, *extra) -> dict:
    with MemorySampler(args.sample_s) as memory:
        start = time.perf_counter()
        frames = loop(args, clips, spp, k, *extra)
        seconds = time.perf_counter() - start
    return {"frames": frames, "seconds": round(seconds, 3), "frames_per_s": round(frames / seconds, 2),
            "ms_per_frame": round(1000 * seconds / frames, 3), "memory": memory.summary()}


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    mi = load_mitsuba(args.backend)
    clips = [waving_sheet(frames=args.frames, n=args.vertices, index=i) for i in range(args.clips)]
    warm = [waving_sheet(frames=max([2, *args.k]), n=args.vertices, index=1000 + i) for i in range(2)]
    modes = [m for m in MODES if not (m == "pooled_frozen" and (args.no_freeze or not mi.variant().startswith("cuda")))]
    rounds = []
    frozen_failure = None
    for spp in args.spp:
        for mode in list(modes):  # untimed: compile (and cache) every kernel first
            try:
                render_loop(args, warm, spp, 1, mode)
            except RuntimeError as e:  # dr.freeze can refuse a scene on some backends: record why, go on
                if mode != "pooled_frozen":
                    raise
                modes.remove(mode)
                print(f"pooled_frozen: {e}", flush=True)
                frozen_failure = f"{type(e).__name__}: {str(e).splitlines()[0][:300]}"
        for k in args.k:
            render_loop(args, warm, spp, k)
        result: dict = {"spp": spp, "samples_per_frame": args.resolution ** 2 * spp,
                        "ceiling": ceiling(args, clips, spp), "render_only": {}}
        print("ceiling", json.dumps(result["ceiling"]), flush=True)
        if frozen_failure:
            result["frozen_failure"] = frozen_failure
        for mode in modes:
            result["render_only"][mode] = timed(render_loop, args, clips, spp, 1, mode)
            print(mode, json.dumps(result["render_only"][mode]), flush=True)
        result["phases"] = {"host_finish": phases(args, clips[:4], spp, modes[-1])}
        unsupported = make_renderer(args, clips[0], 0, spp).device_finish_unsupported
        if unsupported:
            result["phases"]["device_finish"] = {"skipped": unsupported}
        else:
            phases(args, clips[:1], spp, modes[-1], device=True)     # untimed: the finishing kernel compiles
            result["phases"]["device_finish"] = device_row = phases(args, clips[:4], spp, modes[-1], device=True)
            device_row["device_over_host"] = round(
                device_row["ms_per_frame"] / result["phases"]["host_finish"]["ms_per_frame"], 3)
            result["phases"]["device_vs_host"] = device_vs_host(args, clips[:2], spp, modes[-1])
        print("phases", json.dumps(result["phases"]), flush=True)
        if "pooled_frozen" in modes:
            result["frozen_rel_error"] = frozen_error(args, clips, spp)
            print("frozen_rel_error", result["frozen_rel_error"], flush=True)
        for k in args.k:
            result["render_only"][f"batched_k{k}"] = timed(render_loop, args, clips, spp, k)
        for n in args.procs:
            result["render_only"][f"processes_{n}"] = processes_loop(args, spp, n)
            print(f"processes_{n}", json.dumps(result["render_only"][f"processes_{n}"]), flush=True)
        base = result["render_only"]["scene_per_clip"]["frames_per_s"]
        for row in result["render_only"].values():
            row["speedup"] = round(row["frames_per_s"] / base, 3)
            row["samples_per_s_M"] = round(row["frames_per_s"] * result["samples_per_frame"] / 1e6, 1)
        if args.k:
            result["noise_rms"] = noise(args, clips[0], spp, args.k)
            base_rms = result["noise_rms"]["one_frame_per_launch"]
            for k in args.k:
                row = result["render_only"][f"batched_k{k}"]
                ratio = result["noise_rms"][f"batched_k{k}"] / base_rms
                row["noise_rms_ratio"] = round(ratio, 3)
                row["equal_noise_frames_per_s"] = round(row["frames_per_s"] / ratio ** 2, 2)
        if args.write and _stage_importable(result):
            result["with_output"] = {}
            for outputs in args.outputs:
                for device in (True, False):
                    name = outputs if device else f"{outputs}_host_finish"
                    written: dict = {}
                    stage_loop(args, warm, spp, 1, outputs, None, None, device)  # untimed: the stage's kernels
                    row = timed(stage_loop, args, clips, spp, 1, outputs, None, written, device)
                    result["with_output"][name] = {"outputs": written, **row}
                    print(f"with_output {name}", json.dumps(result["with_output"][name]), flush=True)
                result["with_output"][outputs]["over_host_finish"] = round(
                    result["with_output"][outputs]["frames_per_s"]
                    / result["with_output"][f"{outputs}_host_finish"]["frames_per_s"], 3)
                if outputs == "npy":
                    # Two frames in flight against one: the same frames (paired, every byte), and the speed.
                    one, two = {}, {}
                    stage_loop(args, clips, spp, 1, outputs, None, None, True, 1, one)
                    row = timed(stage_loop, args, clips, spp, 1, outputs, None, None, True, 2, two)
                    row["max_code_difference_vs_one_in_flight"] = max(
                        int(np.abs(one[i].astype(np.int16) - two[i]).max()) for i in one)
                    row["over_one_in_flight"] = round(row["frames_per_s"] / result["with_output"]["npy"]["frames_per_s"],
                                                      3)
                    result["with_output"]["npy_two_in_flight"] = row
                    print("with_output npy_two_in_flight", json.dumps(row), flush=True)
                for n in args.write_procs:
                    row = processes_loop(args, spp, n, outputs)
                    result["with_output"][f"{outputs}_processes_{n}"] = row
                    print(f"with_output {outputs}_processes_{n}", json.dumps(row), flush=True)
        top = result["ceiling"]["ceiling_frames_per_s"]
        for group in ("render_only", "with_output"):
            for row in result.get(group, {}).values():
                if top and "frames_per_s" in row:
                    row["ceiling_ratio"] = round(row["frames_per_s"] / top, 3)
        rounds.append(result)
        print(json.dumps({k: v for k, v in result.items() if k != "render_only"}, indent=2), flush=True)
    report = {
        **run_record(argv), "backend": mi.variant(), "mitsuba": mi.__version__,
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "gpu_memory_before_mib": gpu_memory_mib(), "rounds": rounds,
    }
    return save_report(report, args.out, f"render_throughput-{mi.variant()}")


def run_record(argv: list[str] | None) -> dict:
    """The command line, time and machine a benchmark result was made with."""
    return {"command": shlex.join([Path(sys.executable).name, *sys.argv]) if argv is None else shlex.join(argv),
            "time": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": platform.node()}


def save_report(report: dict, out: Path | None, name: str) -> dict:
    """Write ``report`` to ``out`` (default benchmarks/results/<name>-<time>.json) and say where."""
    out = out or RESULTS / f"{name}-{datetime.now(timezone.utc):%Y%m%dT%H%M%S}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
