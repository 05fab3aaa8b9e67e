"""Where a rendered frame's time goes, on the stage's own ClipRenderer (a diagnostic, not a benchmark).

For one backend, resolution and spp, on synthetic waving sheets (render.synthetic):

* ``phases``: per frame, the geometry update (params.update: vertex upload,
  normals, BVH refit), the ``mi.render`` call (tracing the integrator into a
  kernel and launching it; asynchronous on the JIT backends) and the read-back
  (waits for the GPU);
* ``kernels``: Dr.Jit's kernel history over a few frames: launches per frame,
  GPU execution time per frame, and kernels compiled rather than found in the cache;
* ``frozen``: the same loop with ``mi.render`` under ``dr.freeze`` (kernels
  recorded once and replayed; the seed passed as a JIT variable so it does not
  force a new recording);
* ``new_clip``: the cost of a new clip's scene (build + first frame) and
  whether it compiles kernels;
* ``processes``: N processes each running the plain loop, for the aggregate rate.

    python scripts/gpu/render_profile.py --backend cuda_ad_rgb --resolution 224 --spp 16 --out $OUT/profile.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from render.backend import load_mitsuba  # noqa: E402
from render.scene import ClipRenderer  # noqa: E402
from render.synthetic import waving_sheet  # noqa: E402
from render.variants import get_variant  # noqa: E402


def renderer(args, index: int, variant=None) -> ClipRenderer:
    clip = waving_sheet(frames=args.frames, n=args.vertices, index=index)
    return ClipRenderer(clip, variant or get_variant(args.variant), resolution=args.resolution, spp=args.spp,
                        run_seed=0, clip_index=index, backend=args.backend)


def phases(args, r: ClipRenderer) -> dict:
    mi = r.mi
    geo = call = sync = 0.0
    n = 0
    for rep in range(args.reps):
        for t in range(r.clip.num_frames):
            t0 = time.perf_counter()
            r._set_geometry(t)
            t1 = time.perf_counter()
            img = mi.render(r.scene, spp=r.spp, seed=t + 1000 * rep)
            t2 = time.perf_counter()
            np.asarray(img)
            t3 = time.perf_counter()
            geo, call, sync, n = geo + t1 - t0, call + t2 - t1, sync + t3 - t2, n + 1
    total = geo + call + sync
    return {"frames": n, "fps": round(n / total, 1), "ms_geometry": round(1e3 * geo / n, 3),
            "ms_render_call": round(1e3 * call / n, 3), "ms_readback": round(1e3 * sync / n, 3)}


def kernels(args, r: ClipRenderer, frames: int = 5) -> dict:
    import drjit as dr

    frames = min(frames, r.clip.num_frames)
    mi = r.mi
    dr.kernel_history()  # clear
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for t in range(frames):
            r._set_geometry(t)
            np.asarray(mi.render(r.scene, spp=r.spp, seed=t))
        hist = dr.kernel_history()
    jit = [h for h in hist if h.get("type") == dr.KernelType.JIT]
    return {"launches_per_frame": round(len(hist) / frames, 1), "jit_kernels_per_frame": round(len(jit) / frames, 1),
            "gpu_ms_per_frame": round(sum(h.get("execution_time", 0.0) for h in hist) / frames, 3),
            "jit_gpu_ms_per_frame": round(sum(h.get("execution_time", 0.0) for h in jit) / frames, 3),
            "compiled": sum(1 for h in jit if not h.get("cache_hit", True)),
            "codegen_ms_per_frame": round(sum(h.get("codegen_time", 0.0) for h in jit) / frames, 3),
            "largest_kernel_ops": max((h.get("operation_count", 0) for h in jit), default=0)}


def frozen(args, r: ClipRenderer, static: bool = False) -> dict:
    import drjit as dr

    mi = r.mi

    @dr.freeze
    def render(scene, seed):
        return mi.render(scene, spp=r.spp, seed=seed)

    n = 0
    start = None
    for rep in range(args.reps + 1):
        if rep == 1:
            dr.sync_thread()
            start = time.perf_counter()  # the first pass records (and compiles); time the replays
        for t in range(r.clip.num_frames):
            if not static:
                r._set_geometry(t)
            np.asarray(render(r.scene, mi.UInt32(t + 1000 * rep)))
            n += rep >= 1
    seconds = time.perf_counter() - start
    return {"frames": n, "fps": round(n / seconds, 1), "ms_per_frame": round(1e3 * seconds / n, 3),
            "recordings": int(getattr(render, "n_recordings", -1))}


def new_clip(args) -> dict:
    import drjit as dr

    out = []
    for index in (5001, 5002, 5003):
        dr.kernel_history()
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            t0 = time.perf_counter()
            r = renderer(args, index)
            r.render_hdr(0)
            seconds = time.perf_counter() - t0
            hist = dr.kernel_history()
        jit = [h for h in hist if h.get("type") == dr.KernelType.JIT]
        out.append({"seconds": round(seconds, 3), "compiled": sum(1 for h in jit if not h.get("cache_hit", True)),
                    "codegen_ms": round(sum(h.get("codegen_time", 0.0) for h in jit), 1),
                    "backend_ms": round(sum(h.get("backend_time", 0.0) for h in jit), 1)})
    return {"clips": out}


def _worker(args, index: int, seconds: float, queue) -> None:
    r = renderer(args, index)
    r.render_hdr(0)
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        r.render_hdr(n % r.clip.num_frames)
        n += 1
    queue.put(n / (time.perf_counter() - start))


def processes(args) -> dict:
    ctx = mp.get_context("spawn")
    out = {}
    for n in args.procs:
        q = ctx.Queue()
        ps = [ctx.Process(target=_worker, args=(args, 7000 + i, args.proc_seconds, q)) for i in range(n)]
        for p in ps:
            p.start()
        rates = [q.get() for _ in ps]
        for p in ps:
            p.join()
        out[str(n)] = {"fps_total": round(sum(rates), 1), "fps_each": [round(x, 1) for x in rates]}
        print("processes", n, out[str(n)], flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backend", default="auto")
    p.add_argument("--variant", default="paper")
    p.add_argument("--resolution", type=int, default=224)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--vertices", type=int, default=65)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--procs", default="1,4,8")
    p.add_argument("--proc-seconds", type=float, default=15.0)
    p.add_argument("--skip", default="", help="comma-separated sections to skip")
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    args.procs = [int(x) for x in args.procs.split(",") if x]
    skip = set(args.skip.split(","))
    mi = load_mitsuba(args.backend)
    args.backend = mi.variant()
    result: dict = {"settings": {k: str(v) for k, v in vars(args).items()}}

    def section(name, fn):
        if name in skip:
            return
        try:
            result[name] = fn()
        except Exception as e:  # a diagnostic: record and go on
            result[name] = {"error": f"{type(e).__name__}: {e}"}
        print(name, json.dumps(result[name]), flush=True)
        if args.out:
            args.out.write_text(json.dumps(result, indent=2) + "\n")

    r = renderer(args, 0)
    r.render_hdr(0)  # compile
    section("phases", lambda: phases(args, r))
    section("kernels", lambda: kernels(args, r))
    section("frozen", lambda: frozen(args, r))
    r1 = renderer(args, 1)
    r1.render_hdr(0)  # builds the scene (it is built on the first frame)
    section("frozen_static", lambda: frozen(args, r1, static=True))
    base = get_variant(args.variant)
    section("phases_depth2", lambda: phases(args, renderer(args, 2, replace(base, max_depth=2))))
    section("phases_diffuse", lambda: phases(args, renderer(args, 3, get_variant("diffuse"))))
    section("new_clip", lambda: new_clip(args))
    section("processes", lambda: processes(args))


if __name__ == "__main__":
    main()
