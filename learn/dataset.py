"""Rendered clips -> sub-sequence samples, decoded once into a packed frame cache.

Training reads frames many times, so the PNGs of one (variant, setting) are
decoded and resized once into ``cache/<variant>/<setting>/<size>.npy``, a uint8
array of shape (total frames, size, size, 3) opened as a memmap, with
``<size>.json`` beside it saying where each clip's frames start. The index is
written last, so a cache without one is unfinished and is rebuilt.

A sequence of T frames yields sub-sequences starting every ``clip_stride``
frames (``clip_len`` frames each). A clip with a missing or unreadable frame is
reported by a warning naming the clip and the file, and left out.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from tqdm import tqdm

from clothgap import seeding
from clothgap.errors import MissingInputError
from clothgap.runs import Run, atomic_write_json

CACHE_VERSION = 1


class FrameError(RuntimeError):
    """A frame of a clip is missing or cannot be decoded."""


@dataclass(frozen=True)
class CachedClip:
    clip_id: str
    class_index: int
    offset: int          # first row of the clip in the cache array
    num_frames: int


# ---------------------------------------------------------------- reading clips

def frame_paths(clip_dir: Path) -> list[Path]:
    """The expected ``ldr/%04d.png`` paths of a rendered clip (count from meta.json when it says)."""
    meta = json.loads((clip_dir / "meta.json").read_text())
    count = meta.get("num_frames")
    if count is None:
        count = len(list((clip_dir / "ldr").glob("*.png")))
    return [clip_dir / "ldr" / f"{t:04d}.png" for t in range(int(count))]


def read_frames(clip_dir: Path, size: int) -> np.ndarray:
    """All frames of a clip as (T, size, size, 3) uint8, resized with antialiasing.

    Raises FrameError naming the clip and the first frame that is missing or corrupt.
    """
    paths = frame_paths(clip_dir)
    if not paths:
        raise FrameError(f"clip {clip_dir.name}: no frames in {clip_dir / 'ldr'}")
    out = np.empty((len(paths), size, size, 3), np.uint8)
    for t, path in enumerate(paths):
        if not path.is_file():
            raise FrameError(f"clip {clip_dir.name}: frame {path} is missing")
        try:
            with Image.open(path) as img:
                img = img.convert("RGB")
                if img.size != (size, size):
                    img = img.resize((size, size), Image.Resampling.BILINEAR)
                out[t] = np.asarray(img)
        except (OSError, ValueError, SyntaxError) as err:
            raise FrameError(f"clip {clip_dir.name}: frame {path} is unreadable ({err})") from err
    return out


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


def cache_path(run: Run, variant: str, setting: str, size: int) -> Path:
    return run.root / "cache" / variant / setting / f"{size}.npy"


def _signature(render_dir: Path, clip_ids: list[str]) -> list:
    return [[cid, (render_dir / cid / "DONE").stat().st_mtime_ns] for cid in clip_ids]


def build_cache(run: Run, variant: str, setting: str, size: int, progress: bool = True) -> FrameCache:
    """The frame cache of a (variant, setting): reused when it matches the finished clips, else rebuilt."""
    render_dir = run.require(run.render_dir(variant, setting), "render")
    clip_ids = run.done_clips(render_dir)
    if not clip_ids:
        raise MissingInputError(f"no finished clips in {render_dir}: run `clothgap render {run.root}` first")
    array_path = cache_path(run, variant, setting, size)
    index_path = array_path.with_suffix(".json")
    signature = _signature(render_dir, clip_ids)
    if index_path.is_file():
        index = json.loads(index_path.read_text())
        if index.get("version") == CACHE_VERSION and index.get("signature") == signature:
            for cid, reason in index["skipped"].items():
                warnings.warn(f"{reason}; clip left out of {variant}/{setting} (cached)", stacklevel=2)
            return FrameCache(array_path, [CachedClip(**c) for c in index["clips"]])
        index_path.unlink(missing_ok=True)   # stale: rebuilt below

    total = sum(len(frame_paths(render_dir / cid)) for cid in clip_ids)
    array_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = array_path.with_name(f"{array_path.stem}.tmp{os.getpid()}.npy")
    array = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(max(total, 1), size, size, 3))
    clips, skipped, offset = [], {}, 0
    for cid in tqdm(clip_ids, desc=f"cache {variant}/{setting} {size}px", disable=not progress, leave=False):
        try:
            frames = read_frames(render_dir / cid, size)
        except FrameError as err:
            warnings.warn(f"{err}; clip left out of {variant}/{setting}", stacklevel=2)
            skipped[cid] = str(err)
            continue
        array[offset:offset + len(frames)] = frames
        meta = json.loads((render_dir / cid / "meta.json").read_text())
        clips.append(CachedClip(cid, int(meta["class_index"]), offset, len(frames)))
        offset += len(frames)
    array.flush()
    del array
    tmp.replace(array_path)
    atomic_write_json(index_path, {"version": CACHE_VERSION, "size": size, "signature": signature,
                                   "clips": [c.__dict__ for c in clips], "skipped": skipped})
    return FrameCache(array_path, clips)


# ---------------------------------------------------------------- samples

def to_input(frames: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    """uint8 (B, T, 3, H, W) -> float in [0, 1] on ``device`` (the models normalise further)."""
    return frames.to(device, non_blocking=True).float().div_(255)


class SubsequenceDataset(torch.utils.data.Dataset):
    """Sub-sequences of the given clips: items are (uint8 frames (T, 3, H, W), class index).

    With ``augment``, each item gets a random temporal shift of its start frame,
    a random resized crop, a horizontal flip and a colour jitter, the same for
    every frame of the item. The draws depend only on (seed, epoch, item), so a
    resumed run sees the same augmented data as an uninterrupted one.
    """

    def __init__(self, cache: FrameCache, clips: list[str] | dict[str, list[int] | None], clip_len: int,
                 clip_stride: int, augment: bool = False, seed: int = 0):
        """``clips``: clip ids (every window of each), or ``{clip_id: window starts or None}``
        (``learn.split.part_windows``) for a split by sub-sequence."""
        self.cache = cache
        self.clip_len, self.clip_stride = clip_len, clip_stride
        self.augment, self.seed, self.epoch = augment, seed, 0
        self.samples: list[tuple[CachedClip, int]] = []
        windows = clips if isinstance(clips, dict) else dict.fromkeys(clips)
        for cid, chosen in windows.items():
            clip = cache.clips.get(cid)
            if clip is None:
                continue  # not rendered, or left out by the cache with a warning
            starts = subsequence_starts(clip.num_frames, clip_len, clip_stride)
            if chosen is not None:
                chosen = set(chosen)
                starts = [s for s in starts if s in chosen]
            if not starts:
                warnings.warn(f"clip {cid} has {clip.num_frames} frames, fewer than clip_len={clip_len}; left out",
                              stacklevel=2)
            self.samples += [(clip, s) for s in starts]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    @property
    def labels(self) -> list[int]:
        return [clip.class_index for clip, _ in self.samples]

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, int]:
        clip, start = self.samples[i]
        gen = None
        if self.augment:
            gen = torch.Generator().manual_seed(seeding.derive_int(self.seed, i, seeding.TRAIN, "augment", self.epoch))
            shift = int(torch.randint(-(self.clip_stride // 2), self.clip_stride // 2 + 1, (1,), generator=gen))
            start = min(max(start + shift, 0), clip.num_frames - self.clip_len)
        rows = self.cache.frames[clip.offset + start: clip.offset + start + self.clip_len]
        frames = torch.from_numpy(np.array(rows)).permute(0, 3, 1, 2)
        if gen is not None:
            frames = augment_frames(frames, gen)
        return frames.contiguous(), clip.class_index


def augment_frames(frames: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Random resized crop (70-100% of the side), flip and colour jitter of uint8 (T, 3, H, W)."""
    _, _, h, w = frames.shape
    r = torch.rand(7, generator=gen).tolist()
    side = 0.7 + 0.3 * r[0]
    ch, cw = max(1, round(h * side)), max(1, round(w * side))
    y0, x0 = round((h - ch) * r[1]), round((w - cw) * r[2])
    x = frames[:, :, y0:y0 + ch, x0:x0 + cw].float() / 255
    x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    if r[3] < 0.5:
        x = x.flip(-1)
    brightness, contrast, saturation = 0.8 + 0.4 * r[4], 0.8 + 0.4 * r[5], 0.8 + 0.4 * r[6]
    x = x * brightness
    x = (x - x.mean()) * contrast + x.mean()
    grey = x.mean(dim=1, keepdim=True)
    x = (x - grey) * saturation + grey
    return (x.clamp(0, 1) * 255).round().to(torch.uint8)
