"""A rendered clip's tone-mapped frames, the network's input: one uint8 array per clip, PNGs on request.

In a clip folder (``render/<variant>/<setting>/<clip_id>/``)::

    frames.npy     (T, H, W, 3) uint8 sRGB, every frame of the clip; written whole (temporary file, then
                   renamed) before the folder's DONE marker
    ldr/0000.png   the same frames as 8-bit PNGs, when ``render.write_png`` is on; the only frames of
                   clips rendered before frames.npy existed, and of real-video and synthetic clips

With ``render.pack_frames`` the frames go straight into one array a (variant, setting) instead,
``render/<variant>/<setting>/frames-<H>px.npy`` (``FrameStore``: clip index i at rows i*T..(i+1)*T),
and the clip's ``meta.json`` names its rows (``frames_store``); the frame cache at the render
resolution is that array itself (``learn.dataset``), so a setting's frames are on disk once.

``read_clip_frames`` reads any of the three (the clip's array, else its rows of the store, else
its PNGs), so every reader of rendered frames takes old and new folders alike. A clip whose frames
are missing, truncated or of the wrong shape raises ``FrameError`` naming the
file; callers leave the clip out with a warning.

To look at a clip frame by frame when only the array was written::

    python -m render.frames RUN/render/paper/wind-uniform1/c00012 --out frames/   # frames/0000.png ...
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from clothgap.errors import StorageError
from clothgap.files import atomic_path

FRAMES_FILE = "frames.npy"
LDR_DIR = "ldr"
STORE_KEY = "frames_store"          # a packed clip's meta: {"file": store name, "row": first row, "frames": T}


class FrameError(RuntimeError):
    """A frame of a clip is missing or cannot be decoded; the message names the clip and the file."""


def write_frames(clip_dir: Path, frames: np.ndarray) -> Path:
    """Write a clip's (T, H, W, 3) uint8 frames as ``frames.npy``, atomically (no partial file under the name)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"write_frames({clip_dir}): expected (T, H, W, 3) uint8, got {frames.shape} {frames.dtype}")
    path = Path(clip_dir) / FRAMES_FILE
    with atomic_path(path, keep_suffix=True) as tmp, open(tmp, "wb") as f:
        np.save(f, np.ascontiguousarray(frames))
    return path


def store_path(setting_dir: Path, resolution: int) -> Path:
    """Where a (variant, setting)'s packed frames live: ``<setting_dir>/frames-<resolution>px.npy``."""
    return Path(setting_dir) / f"frames-{resolution}px.npy"


class FrameStore:
    """The packed frames of one (variant, setting): a (clips x T, H, W, 3) uint8 ``.npy``, clip index i at rows
    i*T..(i+1)*T, so that render workers write disjoint rows of one file without coordinating.

    The file is made once, at its full size (sparse where the file system allows), under a lock beside it, by
    whichever process needs it first; others open it. Rows are written with ``pwrite``, not through a mapping: a
    full disk is an ``OSError`` (ENOSPC) the render stage turns into a StorageError, where a write into a mapped
    sparse page would kill the process (SIGBUS), and a shared file system gets the bytes of the rows alone. A
    clip's rows are only trusted once its folder is ``DONE``: a killed render leaves rows that the next render
    writes again. ``pending`` is how many clips this process is about to write: their bytes must be free.
    """

    def __init__(self, path: Path, clips: int, frames: int, resolution: int, pending: int | None = None):
        self.path, self.clips, self.frames, self.resolution = Path(path), clips, frames, resolution
        self.shape = (clips * frames, resolution, resolution, 3)
        self.clip_bytes = frames * resolution * resolution * 3
        self.path.parent.mkdir(parents=True, exist_ok=True)
        need = self.clip_bytes * (clips if pending is None else pending)
        free = shutil.disk_usage(self.path.parent).free
        if need > free:
            raise StorageError(f"the packed frames {self.path} need {need / 2**30:.2f} GiB more but "
                               f"{self.path.parent} has {free / 2**30:.2f} GiB free: free some space and run the "
                               f"same command again")
        with open(self.path.with_name(self.path.name + ".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not self.path.is_file():
                self._create()
        again = "remove it and its clips' DONE markers to render them again"
        try:
            mapped = _open_store(self.path)
        except FrameError as err:
            raise FrameError(f"{err}: {again}") from err
        if mapped.shape != self.shape:
            raise FrameError(f"{self.path} holds an array of shape {mapped.shape}, not {self.shape}: it was made "
                             f"for other settings; {again}")
        self._header = mapped.offset

    def _create(self) -> None:
        with atomic_path(self.path, keep_suffix=True) as tmp:
            np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=self.shape)

    def write(self, index: int, frames: np.ndarray) -> dict:
        """Write clip ``index``'s (T, H, W, 3) uint8 frames into its rows; returns the pointer its meta keeps."""
        if frames.shape != (self.frames, self.resolution, self.resolution, 3) or frames.dtype != np.uint8:
            raise ValueError(f"{self.path}: clip {index}'s frames are {frames.shape} {frames.dtype}, its rows "
                             f"take ({self.frames}, {self.resolution}, {self.resolution}, 3) uint8")
        if not 0 <= index < self.clips:
            raise ValueError(f"{self.path}: clip index {index} is outside its {self.clips} clips")
        row = index * self.frames
        data = memoryview(np.ascontiguousarray(frames)).cast("B")
        at, fd = self._header + index * self.clip_bytes, os.open(self.path, os.O_WRONLY)
        try:            # (into the page cache every process shares; the frame cache syncs the file before use)
            while data:
                written = os.pwrite(fd, data, at)
                data, at = data[written:], at + written
        finally:
            os.close(fd)
        return {"file": self.path.name, "row": row, "frames": self.frames}


def png_path(clip_dir: Path, t: int) -> Path:
    return Path(clip_dir) / LDR_DIR / f"{t:04d}.png"


def write_png(clip_dir: Path, t: int, frame: np.ndarray) -> None:
    Image.fromarray(np.ascontiguousarray(frame)).save(png_path(clip_dir, t))


def frame_count(clip_dir: Path, meta: dict) -> int:
    """How many frames a finished clip has: its meta's ``num_frames``, else its array's, else its PNGs."""
    if meta.get("num_frames") is not None:
        return int(meta["num_frames"])
    array = Path(clip_dir) / FRAMES_FILE
    if array.is_file():
        try:
            return int(np.load(array, mmap_mode="r").shape[0])
        except (OSError, ValueError, EOFError, IndexError):
            return 0                    # read_clip_frames names the file
    return len(list((Path(clip_dir) / LDR_DIR).glob("*.png")))


def open_clip_frames(clip_dir: Path, num_frames: int | None = None) -> np.ndarray:
    """A clip's frames as (T, H, W, 3) uint8: ``frames.npy`` opened read-only (memmap), else its decoded PNGs.

    ``num_frames`` (the meta's count) is checked against the array and names the PNGs
    to read (default: every ``ldr/*.png``). Raises FrameError naming the clip and file.
    """
    clip_dir = Path(clip_dir)
    array = clip_dir / FRAMES_FILE
    if not array.is_file():
        pointer = stored_rows(clip_dir)
        return _read_store(clip_dir, pointer, num_frames) if pointer else _read_pngs(clip_dir, num_frames)
    try:
        frames = np.load(array, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:     # truncated, not an .npy, or a header that lies
        raise FrameError(f"clip {clip_dir.name}: frames {array} are unreadable ({err})") from err
    count = frames.shape[0] if num_frames is None else int(num_frames)
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] != count \
            or count == 0:
        raise FrameError(f"clip {clip_dir.name}: frames {array} hold a {frames.dtype} array of shape "
                         f"{frames.shape}, not {count} frames of (H, W, 3) uint8")
    return frames


def stored_rows(clip_dir: Path) -> dict | None:
    """A packed clip's pointer into its setting's store (its meta's ``frames_store``), or None."""
    try:
        return json.loads((Path(clip_dir) / "meta.json").read_text()).get(STORE_KEY)
    except (OSError, ValueError):
        return None


def _open_store(path: Path) -> np.ndarray:
    """A packed array, read-only: a FrameError naming it unless it reads as (N, H, W, 3) uint8."""
    try:
        store = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise FrameError(f"packed frames {path} are unreadable ({err})") from err
    if store.dtype != np.uint8 or store.ndim != 4 or store.shape[-1] != 3:
        raise FrameError(f"packed frames {path} hold a {store.dtype} array of shape {store.shape}, not (N, H, W, 3) "
                         f"uint8")
    return store


def _rows(store: np.ndarray, path: Path, pointer: dict) -> tuple[int, int]:
    """(first row, frame count) of a clip's ``pointer`` into ``store``: a FrameError unless the store holds them."""
    try:
        row, count = int(pointer["row"]), int(pointer["frames"])
    except (KeyError, TypeError, ValueError) as err:
        raise FrameError(f"a pointer into {path} without its rows ({pointer!r})") from err
    if count == 0 or row < 0 or row + count > store.shape[0]:
        raise FrameError(f"rows {row}..{row + count} are outside {path}'s {store.shape[0]}")
    return row, count


def _read_store(clip_dir: Path, pointer: dict, num_frames: int | None) -> np.ndarray:
    path = Path(clip_dir).parent / str(pointer.get("file"))
    try:
        store = _open_store(path)
        row, count = _rows(store, path, pointer)
    except FrameError as err:
        raise FrameError(f"clip {Path(clip_dir).name}: {err}") from err
    if num_frames is not None and int(num_frames) != count:
        raise FrameError(f"clip {Path(clip_dir).name}: its meta says {num_frames} frames, its rows of {path} {count}")
    return store[row:row + count]


def shared_store(setting_dir: Path, pointers: Sequence[dict | None], size: int) -> Path | None:
    """The one packed array of ``setting_dir`` that holds every clip's rows (``pointers``: the clips'
    ``frames_store``) at ``size`` x ``size``, or None: some clip has none (a frames.npy or PNGs instead), they name
    different arrays, the array is of another size, or it does not read (readers then name the clip)."""
    if not pointers or any(not isinstance(p, dict) for p in pointers) or len({p.get("file") for p in pointers}) != 1:
        return None
    path = Path(setting_dir) / str(pointers[0]["file"])
    try:
        store = _open_store(path)
        for pointer in pointers:
            _rows(store, path, pointer)
    except FrameError:
        return None
    return path if store.shape[1:3] == (size, size) else None


def copy_frames_into(array_path: str, tasks: list[tuple[str, int, int]], size: int) -> dict:
    """Copy clips' frames into rows of the (N, size, size, 3) uint8 ``.npy`` at ``array_path`` (opened read-write):
    each task is a clip folder, its frame count and its first row; frames of another size are resized. A pool's
    task (``learn.dataset.build_cache``: this module imports no torch, so spawned workers start quickly). Returns
    how many clips it handled and, by clip id, why each clip it could not read was left out."""
    # No flush here: the rows are in the host's page cache, which every process mapping the file shares; the
    # builder syncs the whole file once at the end (a flush a call would write each chunk to disk before the next).
    array = np.load(array_path, mmap_mode="r+")
    skipped = {}
    for clip_dir, count, offset in tasks:
        try:
            frames = open_clip_frames(Path(clip_dir), count)
            rows = array[offset:offset + len(frames)]
            if frames.shape[1:3] == (size, size):
                rows[:] = frames        # the render resolution: the clip's array as it is
            else:
                resize_frames(frames, size, out=rows)
        except FrameError as err:
            skipped[Path(clip_dir).name] = str(err)
    del array
    return {"clips": len(tasks), "skipped": skipped}


def read_clip_frames(clip_dir: Path, num_frames: int | None = None, size: int | None = None) -> np.ndarray:
    """A clip's frames as an owned (T, H, W, 3) uint8 array, each resized to (size, size) when ``size`` is given.

    Resizing is PIL's bilinear on the uint8 frame, the same for the array and the PNGs,
    so both give the same bytes for the same frames.
    """
    frames = open_clip_frames(clip_dir, num_frames)
    if size is None or frames.shape[1:3] == (size, size):
        return np.array(frames)
    return resize_frames(frames, size)


def resize_frames(frames: np.ndarray, size: int, out: np.ndarray | None = None) -> np.ndarray:
    """(T, H, W, 3) uint8 -> (T, size, size, 3), frame by frame through PIL's bilinear filter."""
    out = np.empty((len(frames), size, size, 3), np.uint8) if out is None else out
    for t, frame in enumerate(frames):
        out[t] = _resized(Image.fromarray(np.asarray(frame)), size)
    return out


def _resized(img: Image.Image, size: int) -> np.ndarray:
    if img.size != (size, size):
        img = img.resize((size, size), Image.Resampling.BILINEAR)
    return np.asarray(img)


def _read_pngs(clip_dir: Path, num_frames: int | None) -> np.ndarray:
    count = len(list((clip_dir / LDR_DIR).glob("*.png"))) if num_frames is None else int(num_frames)
    if count == 0:
        raise FrameError(f"clip {clip_dir.name}: no frames in {clip_dir / LDR_DIR} and no {FRAMES_FILE}")
    frames = None
    for t in range(count):
        path = png_path(clip_dir, t)
        if not path.is_file():
            raise FrameError(f"clip {clip_dir.name}: frame {path} is missing")
        try:
            with Image.open(path) as img:
                rgb = np.asarray(img.convert("RGB"))
        except (OSError, ValueError, SyntaxError) as err:
            raise FrameError(f"clip {clip_dir.name}: frame {path} is unreadable ({err})") from err
        if frames is None:
            frames = np.empty((count, *rgb.shape), np.uint8)
        elif rgb.shape != frames.shape[1:]:
            raise FrameError(f"clip {clip_dir.name}: frame {path} is {rgb.shape[1]}x{rgb.shape[0]} pixels, "
                             f"frame 0 {frames.shape[2]}x{frames.shape[1]}")
        frames[t] = rgb
    return frames


def export_png(clip_dir: Path, out_dir: Path) -> list[Path]:
    """Write a clip's frames to ``out_dir/%04d.png`` (from its array or its PNGs); returns the paths."""
    frames = open_clip_frames(clip_dir)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for t, frame in enumerate(frames):
        paths.append(out_dir / f"{t:04d}.png")
        Image.fromarray(np.asarray(frame)).save(paths[-1])
    return paths


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m render.frames",
                                description="Write a rendered clip's frames (frames.npy or ldr/) as PNG files.")
    p.add_argument("clip_dir", type=Path, help="a rendered clip folder, e.g. RUN/render/paper/wind-uniform1/c00012")
    p.add_argument("--out", type=Path, required=True, help="folder for 0000.png ...")
    args = p.parse_args(argv)
    try:
        paths = export_png(args.clip_dir, args.out)
    except FrameError as err:
        raise SystemExit(f"error: {err}") from None
    print(f"wrote {len(paths)} frames to {args.out}")


if __name__ == "__main__":
    main()
