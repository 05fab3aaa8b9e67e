"""Rendered clips -> sub-sequence samples, packed once into a frame cache.

Training reads frames many times, so the frames of one (variant, setting) are
packed once into ``cache/<variant>/<setting>/<size>.npy``, a uint8 array of
shape (total frames, size, size, 3) opened as a memmap, with ``<size>.json``
beside it saying where each clip's frames start. Each clip's frames come from
its ``frames.npy`` (copied as they are, or resized when ``size`` is not the
render resolution), or, in clip folders without one, from its PNGs
(``render.frames.read_clip_frames``). The index is written last, so a cache
without one is unfinished and is rebuilt. When every clip's frames went into
its setting's packed array at render time (``render.pack_frames``) and ``size``
is the render resolution, nothing is copied: the index points into that array
(its ``array``, relative to the run).

A sequence of T frames yields sub-sequences starting every ``clip_stride``
frames (``clip_len`` frames each); ``learn.windows`` cuts them into batches. A
clip with a missing, truncated or unreadable frame file is reported by a
warning naming the clip and the file, and left out.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from clothgap.errors import MissingInputError, StorageError
from clothgap.files import atomic_path
from clothgap.parallel import chunk_size, pool_map, pool_size
from clothgap.runs import Run, atomic_write_json, read_meta
from render.frames import STORE_KEY, copy_frames_into, frame_count, read_clip_frames, shared_store

CACHE_VERSION = 2                  # 2: an index may point into a packed array (``array``)
# A pool builds a cache of at least this many clips on a host of at least this many CPUs: copying is bound by
# memory and disk, and on 2 cores a pool lost (benchmarks/train_inputs.py); spawning costs ~1 s.
POOL_MIN_CLIPS = 256
POOL_MIN_CPUS = 8
IN_PROCESS_CHUNK = 64       # clips a call copies in this process (the progress bar moves between calls)


@dataclass(frozen=True)
class CachedClip:
    clip_id: str
    class_index: int
    offset: int          # first row of the clip in the cache array
    num_frames: int


# ---------------------------------------------------------------- reading clips

def read_frames(clip_dir: Path, size: int, meta: dict | None = None) -> np.ndarray:
    """All frames of a clip as (T, size, size, 3) uint8, resized with antialiasing.

    Raises FrameError naming the clip and the first frame file that is missing or corrupt.
    """
    meta = read_meta(clip_dir, "render") if meta is None else meta
    return read_clip_frames(clip_dir, frame_count(clip_dir, meta), size)


def subsequence_starts(num_frames: int, clip_len: int, stride: int) -> list[int]:
    """Start frames of the ``clip_len``-frame windows of a sequence, every ``stride`` frames."""
    if clip_len < 1 or stride < 1:
        raise ValueError(f"clip_len ({clip_len}) and clip_stride ({stride}) must be at least 1")
    return list(range(0, num_frames - clip_len + 1, stride))


# ---------------------------------------------------------------- the frame cache

class FrameCache:
    """The decoded frames of one (variant, setting) at one size, and where each clip lies."""

    def __init__(self, array_path: Path, clips: list[CachedClip]):
        self.array_path = Path(array_path)
        self.clips = {c.clip_id: c for c in clips}
        self._frames: np.ndarray | None = None

    @property
    def frames(self) -> np.ndarray:
        # Opened lazily so that a pickled cache (DataLoader workers) reopens its own memmap.
        if self._frames is None:
            self._frames = np.load(self.array_path, mmap_mode="r")
        return self._frames

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_frames": None}


def _signature(render_dir: Path, clip_ids: list[str]) -> list:
    return [[cid, (render_dir / cid / "DONE").stat().st_mtime_ns] for cid in clip_ids]


def build_cache(run: Run, variant: str, setting: str, size: int, progress: bool = True,
                processes: int | None = None) -> FrameCache:
    """The frame cache of a (variant, setting): reused when it matches the finished clips, else rebuilt.

    Clips are copied (or resized) into the array in a spawned process pool when there are many (``processes``
    None picks by ``clothgap.parallel.pool_size``; 0 copies them here), each clip at the row where it would be in
    any case; a clip left out leaves its rows unused."""
    render_dir = run.require(run.render_dir(variant, setting), "render")
    clip_ids = run.done_clips(render_dir)
    if not clip_ids:
        raise MissingInputError(f"no finished clips in {render_dir}: run `clothgap render {run.root}` first")
    array_path = run.frame_cache_path(variant, setting, size)
    index_path = array_path.with_suffix(".json")
    signature = _signature(render_dir, clip_ids)
    if index_path.is_file():
        index = json.loads(index_path.read_text())
        if index.get("version") == CACHE_VERSION and index.get("signature") == signature:
            for cid, reason in index["skipped"].items():
                warnings.warn(f"{reason}; clip left out of {variant}/{setting} (cached)", stacklevel=2)
            array = run.root / index["array"] if "array" in index else array_path
            return FrameCache(array, [CachedClip(**c) for c in index["clips"]])
        index_path.unlink(missing_ok=True)   # stale: rebuilt below

    metas = {cid: read_meta(render_dir / cid, "render") for cid in clip_ids}
    store = shared_store(render_dir, [m.get(STORE_KEY) for m in metas.values()], size)
    if store is not None:
        # Every clip is in its setting's packed array at this size: index it in place, on disk first (as a
        # copied cache is before it is renamed into place).
        with open(store, "rb") as f:
            os.fsync(f.fileno())
        clips = [CachedClip(cid, int(metas[cid]["class_index"]), int(metas[cid][STORE_KEY]["row"]),
                            int(metas[cid][STORE_KEY]["frames"])) for cid in clip_ids]
        array_path.parent.mkdir(parents=True, exist_ok=True)
        array_path.unlink(missing_ok=True)      # a copy made before the clips were packed: not kept twice
        atomic_write_json(index_path, {"version": CACHE_VERSION, "size": size, "signature": signature,
                                       "array": str(store.relative_to(run.root)),
                                       "clips": [c.__dict__ for c in clips], "skipped": {}})
        return FrameCache(store, clips)
    counts = [frame_count(render_dir / cid, metas[cid]) for cid in clip_ids]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(int).tolist()
    total = offsets[-1]
    array_path.parent.mkdir(parents=True, exist_ok=True)
    # A memmap written past a full disk dies of SIGBUS with no message: check the space first.
    need, free = total * size * size * 3, shutil.disk_usage(array_path.parent).free
    if need > free:
        raise StorageError(f"the frame cache {array_path} needs {need / 2**30:.2f} GiB but {array_path.parent} "
                           f"has {free / 2**30:.2f} GiB free: free some space and run the same command again")
    tasks = [(str(render_dir / cid), counts[i], offsets[i]) for i, cid in enumerate(clip_ids)]
    if processes is None:
        processes = pool_size(len(tasks), POOL_MIN_CLIPS, POOL_MIN_CPUS)
    skipped: dict[str, str] = {}
    # A killed or failed build leaves no multi-GB temporary behind (a kill -9's is removed by the next build).
    with atomic_path(array_path, keep_suffix=True) as tmp:
        np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(max(total, 1), size, size, 3))  # sized, zero
        bar = tqdm(total=len(tasks), desc=f"cache {variant}/{setting} {size}px", disable=not progress, leave=False)
        pooled = processes > 1 and len(tasks) > 1
        step = chunk_size(len(tasks), processes) if pooled else IN_PROCESS_CHUNK
        chunks = [tasks[i:i + step] for i in range(0, len(tasks), step)]
        parts = pool_map(copy_frames_into, [str(tmp)] * len(chunks), chunks, [size] * len(chunks),
                         processes=processes, chunksize=1)
        for part in parts:
            skipped.update(part["skipped"])
            bar.update(part["clips"])
        bar.close()
        with open(tmp, "rb+") as f:          # every process's rows on disk before the array is renamed into place
            os.fsync(f.fileno())
    for cid, reason in skipped.items():
        warnings.warn(f"{reason}; clip left out of {variant}/{setting}", stacklevel=2)
    clips = [CachedClip(cid, int(metas[cid]["class_index"]), offsets[i], counts[i])
             for i, cid in enumerate(clip_ids) if cid not in skipped]
    atomic_write_json(index_path, {"version": CACHE_VERSION, "size": size, "signature": signature,
                                   "clips": [c.__dict__ for c in clips], "skipped": skipped})
    return FrameCache(array_path, clips)


# ---------------------------------------------------------------- samples

def to_input(frames: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    """uint8 (B, T, 3, H, W) -> float in [0, 1] on ``device`` (the models normalise further)."""
    return frames.to(device, non_blocking=True).float().div_(255)
