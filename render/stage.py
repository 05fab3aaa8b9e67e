"""The render stage: every finished sim clip, under every variant of the run, to frames on disk.

``run_render(run)`` walks ``variants x settings x done sim clips``, skips clip
folders that are already finished (``DONE``), and renders the rest, one Mitsuba
scene per clip (``render.scene.ClipRenderer``), ``render.frames_per_launch`` frames
per Mitsuba launch (``render.batch``; one per launch for lightings it cannot
batch). At one frame per launch on cuda_ad_rgb and llvm_ad_rgb, each frame is
composited, tone-mapped and encoded to 8-bit sRGB on the device
(``render.device_finish``) and only the uint8 frame is read back (the linear
RGBA too when EXRs are written); otherwise (scalar_rgb, sensor noise, batched
launches) the host does it from the read-back RGBA, with the same bytes. A
pool of ``render.writer_threads`` threads does the host's part (composite and
tone map on the host path, EXR/PNG writes when asked) while the next frames
render. Each clip folder gets::

    frames.npy         (T, H, W, 3) uint8 sRGB, composited and tone-mapped: what the network reads
                       (render.frames; the learn stage packs these arrays into its frame cache)
    ldr/0000.png ...   the same frames as PNGs, when render.write_png
    hdr/0000.exr ...   linear RGBA cloth radiance (float32), when render.write_hdr
    meta.json          the sim meta + variant, render settings (backend, seeds, draws), num_frames
    DONE               written last

Tone mapping works on the frame in memory, so a variant's tone curve needs no
EXR; PNG and EXR are for looking at a run (``python -m render.frames`` writes
PNGs from the array afterwards). A clip that fails to render gets a ``FAILED``
file with the reason and no ``DONE``; the stage goes on with the next clip and
lists the failures in its summary, so one bad clip does not cost a long run.

The jobs go look by look (variant-major), and a look's scenes and kernels are freed once its last clip is done
(``release_look``): a worker's memory no longer adds up over a study's datasets, and a look renders as fast after
eleven others as it would first (kept, the looks' render times rose over the looks: benchmarks/render_pool_memory.py).
"""

from __future__ import annotations

import ctypes
import gc
import shutil
import time
import traceback
import warnings
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from dataclasses import replace
from concurrent.futures import Executor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from clothgap.runs import (Run, atomic_write_json, clip_id as clip_name, fresh_dir, is_done, mark_done, select_clips,
                           storage_error)
from render.backend import load_mitsuba
from render.backgrounds import Backgrounds
from render.batch import BatchRenderer, batchable
from render.config import RenderConfig, frames_per_launch
from render.exr import write_exr
from render.frames import LDR_DIR, STORE_KEY, FrameStore, store_path, write_frames, write_png
from render.scene import ClipRenderer, clear_scene_pools
from render.variants import RenderVariant, get_variant
from render.video import compress_frames
from sim.clip import SimClip

FAILED = "FAILED"

# Whether render_jobs frees a look's scenes and kernels once its last clip is done (release_look). Off only to
# measure what it saves (benchmarks/render_pool_memory.py --keep-looks).
RELEASE_LOOKS = True


def release_look() -> None:
    """Free what the looks rendered so far hold in this process.

    Each look (variant) has scene structures of its own: its pooled scenes (``render.scene.ScenePool``) with their
    frozen renders, and the kernels traced for them, which Dr.Jit keeps for the life of the process (on CUDA an
    OptiX pipeline for each structure). A render worker goes through a study's looks one after another and never
    comes back to one, so without this its memory grows with the number of datasets (issue 14). Every pool is
    emptied first (Dr.Jit's flush is process-wide), so that no frozen render is left to replay a flushed kernel;
    the next look compiles its own kernels anyway, the ones it shares with the last look come from Dr.Jit's disk
    cache.
    """
    clear_scene_pools()
    gc.collect()                                  # scenes held in reference cycles go now, not at some later pass
    import drjit as dr  # imported here: render.backend picks libLLVM before drjit is first imported
    dr.sync_thread()
    dr.flush_kernel_cache()
    dr.flush_malloc_cache()
    _malloc_trim()


def _malloc_trim() -> None:
    """Hand the heap pages freed above back to the OS (glibc keeps them for reuse otherwise); elsewhere a no-op."""
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


def clip_index_of(clip: SimClip, clip_dir: Path) -> int:
    """The clip's index (seeds are per index): from its meta, else from its folder name (``c00012``)."""
    if "index" in clip.meta:
        return int(clip.meta["index"])
    try:
        return int(clip_dir.name.lstrip("c"))
    except ValueError:
        raise ValueError(f"{clip_dir}: meta.json has no 'index' and the folder name is not a clip id") from None


def render_clip(clip: SimClip, variant: RenderVariant, out_dir: Path, *, config: RenderConfig, run_seed: int,
                clip_index: int, backgrounds: Backgrounds | None = None, writer: Executor | None = None,
                device_finish: bool = True, store: FrameStore | None = None) -> dict:
    """Render all frames of ``clip`` into ``out_dir`` (frames.npy, ldr/, hdr/, meta.json); returns the meta written.

    With a ``store`` (``render.pack_frames``) the frames go into the clip's rows of it instead of frames.npy,
    and the meta names those rows (``frames_store``).

    ``writer`` runs the per-frame host work (composite and tone map on the host
    path, EXR and PNG writes) beside the renderer; without one, a pool of
    ``config.writer_threads`` lives for this clip. All of the clip's writes have
    finished when this returns. Frames are finished on the device where it can
    (see the module's docstring); ``device_finish=False`` keeps the host path
    (the benchmark's reference). Does not write ``DONE``: the caller marks the
    folder finished once it is satisfied.
    """
    start = time.perf_counter()
    renderer = ClipRenderer(clip, variant, resolution=config.resolution, spp=config.spp, run_seed=run_seed,
                            clip_index=clip_index, backend=config.backend, backgrounds=backgrounds,
                            reuse_scenes=config.reuse_scenes, freeze=config.freeze)
    frames, per_launch, on_host, unbatched = _frame_source(renderer, config, device_finish)
    compress = variant.video_crf > 0
    png = config.write_png
    (out_dir / LDR_DIR if png else out_dir).mkdir(parents=True, exist_ok=True)
    ldr = _finish_frames(renderer, frames, out_dir, config, compress, writer)
    if compress:
        ldr = np.stack(compress_frames(list(ldr), crf=variant.video_crf, fps=float(clip.meta.get("fps", 25.0))))
        if png:
            for t, frame in enumerate(ldr):
                write_png(out_dir, t, frame)
    # (a clip of another length than its store's slots keeps a frames.npy)
    pointer = store.write(clip_index, ldr) if store is not None and len(ldr) == store.frames else None
    if pointer is None:
        write_frames(out_dir, ldr)
    meta = dict(clip.meta)
    meta.update({
        "variant": variant.name,
        "render": {**variant.settings(), "resolution": config.resolution, "spp": config.spp,
                   "write_hdr": config.write_hdr, "write_png": png, **renderer.info,
                   "scene_builds": renderer.rebuilds, "frames_per_launch": per_launch,
                   "finished_on": "host" if on_host else "device",
                   **({"host_finish_because": on_host} if on_host else {}),
                   **({"unbatched_because": unbatched} if unbatched else {}),
                   "seconds": round(time.perf_counter() - start, 3)},
        "num_frames": clip.num_frames,
        **({STORE_KEY: pointer} if pointer else {}),
    })
    atomic_write_json(out_dir / "meta.json", meta)
    return meta


def _frame_source(renderer: ClipRenderer, config: RenderConfig, device_finish: bool):
    """How the clip's frames are rendered: ``(frames, frames per launch, why they are finished on the host or
    None, why they are not batched or None)``; ``frames`` yields ``(t, linear RGBA or None, uint8 frame or None)``."""
    per_launch = frames_per_launch(config, renderer.mi.variant())
    unbatched = batchable(renderer) if per_launch > 1 else None
    on_host = (renderer.device_finish_unsupported if device_finish else "device_finish=False") \
        or ("several frames per launch" if per_launch > 1 and unbatched is None else None)
    if per_launch > 1 and unbatched is None:
        batch = BatchRenderer(renderer, per_launch)
        frames, per_launch = ((t, hdr, None) for t, hdr in batch.hdr_frames()), batch.k
    elif on_host:
        frames, per_launch = ((t, renderer.render_hdr(t), None) for t in range(renderer.clip.num_frames)), 1
    else:
        frames, per_launch = _finished_on_device(renderer, config.write_hdr, config.frames_in_flight), 1
    return frames, per_launch, on_host, unbatched


def _finish_frames(renderer: ClipRenderer, frames, out_dir: Path, config: RenderConfig, compress: bool,
                   writer: Executor | None) -> np.ndarray:
    """The clip's 8-bit frames (T, H, W, 3): each frame finished on the host where it still needs it, its EXR and
    PNG written, on ``writer`` (or a pool of its own); returns once every write has finished."""
    png = config.write_png
    res = config.resolution
    ldr = np.empty((renderer.clip.num_frames, res, res, 3), np.uint8)

    def finish(t: int, hdr: np.ndarray | None, frame: np.ndarray | None) -> None:
        ldr[t] = renderer.finish(hdr, t) if frame is None else frame
        if config.write_hdr:
            write_exr(out_dir / "hdr" / f"{t:04d}.exr", hdr)
        if png and not compress:
            write_png(out_dir, t, ldr[t])

    own = writer is None
    pool = ThreadPoolExecutor(max(1, config.writer_threads), thread_name_prefix="render-writer") if own else writer
    try:
        pending = []
        for t, hdr, frame in frames:
            if frame is not None and not config.write_hdr and not (png and not compress):
                ldr[t] = frame      # nothing left to do on the host: no round trip through the pool
            else:
                pending.append(pool.submit(finish, t, hdr, frame))
        for f in pending:
            f.result()  # re-raises a failed write; the clip is then FAILED
    finally:
        if own:
            pool.shutdown(wait=True)
    return ldr


def _finished_on_device(renderer: ClipRenderer, hdr: bool, in_flight: int = 1):
    """``(t, linear RGBA or None, uint8 frame)`` for every frame, finished on the device (RGBA only with ``hdr``);
    up to ``in_flight`` frames are launched before the oldest is read back."""
    launched: deque = deque()

    def oldest():
        done, handle = launched.popleft()
        frame, linear = renderer.read_finished(handle, hdr=hdr)
        return done, linear, frame

    for t in range(renderer.clip.num_frames):
        launched.append((t, renderer.launch_finished(t)))
        if len(launched) >= in_flight:
            yield oldest()
    while launched:
        yield oldest()


def run_render(run: Run, progress: bool = True, indices: Sequence[int] | None = None) -> dict:
    """Render every finished sim clip of ``run`` under each of its variants; returns a summary.

    Summary: ``backend``, ``rendered``, ``skipped`` (already done), ``failed``
    (``[{variant, setting, clip_id, error}]``), ``skipped_backgrounds`` (unreadable
    background files), ``seconds``, ``seconds_per_clip``, ``seconds_per_frame``.
    ``indices`` limits the work to those clip indices (one shard of ``clothgap.executor``).
    """
    config = run.config.render
    variants = [get_variant(name) for name in config.variants]  # unknown names fail before any work
    wanted = None if indices is None else {clip_name(i) for i in select_clips(run.config.sim.num_clips(), indices)}
    jobs = [(variant, setting, run.sim_dir(setting) / clip_id, run.render_dir(variant.name, setting) / clip_id)
            for variant in variants
            for setting in config.settings_of(variant.name, run.config.sim.settings())
            for clip_id in run.done_clips(run.sim_dir(setting)) if wanted is None or clip_id in wanted]
    return render_jobs(run, jobs, progress, variants=variants)


def merge_shard_summaries(parts: list[dict]) -> dict:
    """One ``run_render`` summary from the summaries of its shards (``indices=``, run by ``clothgap.executor``):
    counts add up, failures and skipped backgrounds are listed together, the per-clip and per-frame times are
    weighted by the clips each shard rendered; ``seconds`` is left to the caller, who timed the whole."""
    merged = {"backend": next((p["backend"] for p in parts if "backend" in p), None),
              "rendered": sum(p.get("rendered", 0) for p in parts),
              "skipped": sum(p.get("skipped", 0) for p in parts),
              "failed": [f for p in parts for f in p.get("failed", [])],
              "frames": sum(p.get("frames", 0) for p in parts),
              "skipped_backgrounds": {k: v for p in parts for k, v in p.get("skipped_backgrounds", {}).items()},
              "seconds": 0.0}
    render_seconds = sum(p.get("seconds_per_clip", 0.0) * p.get("rendered", 0) for p in parts)
    if merged["rendered"]:
        merged["seconds_per_clip"] = round(render_seconds / merged["rendered"], 4)
        merged["seconds_per_frame"] = round(render_seconds / merged["frames"], 5)
    return merged


def render_jobs(run: Run, jobs: list[tuple[RenderVariant, str, Path, Path]], progress: bool = True,
                label: str = "render", variants: Sequence[RenderVariant] | None = None,
                config: RenderConfig | None = None) -> dict:
    """Render each ``(variant, setting, sim clip folder, output folder)`` not finished yet (summary as run_render).

    Shared by ``run_render`` and the measured-fabric set (``render_measured``): the
    same renderer, seeds (the sim meta's clip index), meta, FAILED and DONE markers.
    ``config`` replaces the run's render settings (the measured set forces PNGs).
    Clips render one after another: Mitsuba's symbolic virtual calls trace every shape of the process, so a
    second thread updating its own scene breaks (and on llvm_ad_rgb deadlocks) the first one's render.
    """
    config = config or run.config.render
    mi = load_mitsuba(config.backend)
    if variants is None:
        variants = list({v.name: v for v, *_ in jobs}.values())
    backgrounds = {v.name: Backgrounds(v, config.resolution) for v in variants}
    # With packing, one store a (variant, setting) folder, made or opened before any clip renders: a full disk or
    # a store of other settings stops the stage instead of failing each clip.
    pending = Counter(out.parent for *_, out in jobs if config.pack_frames and not is_done(out))
    stores = {folder: FrameStore(store_path(folder, config.resolution), run.config.sim.num_clips(),
                                 run.config.sim.frames, config.resolution, pending=count)
              for folder, count in pending.items()}
    summary: dict = {"backend": mi.variant(), "rendered": 0, "skipped": 0, "failed": [], "frames": 0}
    start = time.perf_counter()
    render_seconds = 0.0
    writer = ThreadPoolExecutor(max(1, config.writer_threads), thread_name_prefix="render-writer")
    last_job_of = {v.name: i for i, (v, *_) in enumerate(jobs)}
    rendered_since_release = False
    for i, (variant, setting, clip_dir, out_dir) in enumerate(tqdm(jobs, desc=label, unit="clip",
                                                                   disable=not progress)):
        if RELEASE_LOOKS and rendered_since_release and last_job_of[jobs[i - 1][0].name] == i - 1:
            release_look()                        # the previous look is finished in this call
            rendered_since_release = False
        if is_done(out_dir):
            summary["skipped"] += 1
            continue
        fresh_dir(out_dir)
        rendered_since_release = True             # (a clip that fails may have built its scene too)
        clip_start = time.perf_counter()
        try:
            clip = SimClip.load(clip_dir)
            meta = render_clip(clip, variant, out_dir, config=config, run_seed=run.config.seed,
                               clip_index=clip_index_of(clip, clip_dir), backgrounds=backgrounds[variant.name],
                               writer=writer, store=stores.get(out_dir.parent))
        except Exception as e:  # one bad clip must not stop the run; it is recorded and reported
            storage = storage_error(e, out_dir) if isinstance(e, OSError) else None
            if storage is not None:
                # A full or read-only disk fails every clip alike: stop, leaving no half-written frames.
                writer.shutdown(wait=True)
                shutil.rmtree(out_dir, ignore_errors=True)
                raise storage from None
            reason = f"{type(e).__name__}: {e}"
            try:
                atomic_write_json(out_dir / FAILED, {"error": reason, "traceback": traceback.format_exc()})
            except OSError as marker:
                # The clip has no DONE either way, so it is redone on the next run; say why there is no marker.
                reason += f" (its FAILED marker could not be written: {marker.strerror or marker})"
            summary["failed"].append({"variant": variant.name, "setting": setting, "clip_id": clip_dir.name,
                                      "error": reason})
            warnings.warn(f"{label} {variant.name}/{setting}/{clip_dir.name} failed: {reason}", stacklevel=2)
            continue
        render_seconds += time.perf_counter() - clip_start
        mark_done(out_dir, {"frames": meta["num_frames"]})
        summary["rendered"] += 1
        summary["frames"] += meta["num_frames"]
    writer.shutdown(wait=True)
    if RELEASE_LOOKS and rendered_since_release:
        release_look()      # this call's work is done; a later one (another shard, the measured set) builds its own
    summary["skipped_backgrounds"] = {f: r for b in backgrounds.values() for f, r in b.skipped.items()}
    summary["seconds"] = round(time.perf_counter() - start, 3)
    if summary["rendered"]:
        summary["seconds_per_clip"] = round(render_seconds / summary["rendered"], 4)
        summary["seconds_per_frame"] = round(render_seconds / summary["frames"], 5)
    return summary


def render_measured(run: Run, variant: str, clips: Mapping[str, Sequence[str]] | None = None,
                    progress: bool = True) -> dict:
    """Render the run's finished measured-fabric sim clips (``sim.measured``) under ``variant``.

    ``RUN/measured/sim/<setting>/<fabric>-<n>/`` -> ``RUN/measured/render/<variant>/<setting>/<fabric>-<n>/``,
    the render clip contract (the meta keeps the sim meta's ``fabric``); ``clips`` (setting -> clip folder
    names) limits it to those settings and clips. Resolution, spp and backend are the run's.
    """
    chosen = get_variant(variant)
    if clips is None:
        clips = {s: None for s in run.config.sim.settings()}
    jobs = [(chosen, setting, run.measured_sim_dir(setting) / name, run.measured_render_dir(variant, setting) / name)
            for setting, names in clips.items()
            for name in run.done_clips(run.measured_sim_dir(setting)) if names is None or name in names]
    # The measured set is read as image folders through the real-video path (eval.measured): it keeps PNGs.
    return render_jobs(run, jobs, progress, label="render measured", variants=[chosen],
                       config=replace(run.config.render, write_png=True, pack_frames=False))
