"""Predictions of a trained model on rendered clips of any variant (for eval).

Frames are read straight from the clip folders (not the training frame cache),
resized to the model's image size, and cut into the sub-sequences the model was
trained on (``clip_len`` frames every ``clip_stride``, no augmentation).
``CachedPredictor`` reads a clip list once for the models that predict on it in a row.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd
import torch

from clothgap.errors import InputError, MissingInputError, UserError
from clothgap.runs import read_meta
from learn.dataset import FrameCache, read_frames, subsequence_starts, to_input
from learn.models import ClipClassifier, build_model
from learn import predictions
from learn.train import resolve_device
from learn.windows import WindowSet
from render.frames import FrameError


CHECKPOINT_KEYS = ("model", "model_name", "model_args", "config")


def _corrupt(path: Path, why: str) -> InputError:
    return InputError(f"checkpoint {path} {why}: retrain it (delete {path.parent} and run `clothgap train` "
                      "on its run again)")


def load_checkpoint(train_dir: Path | str) -> dict:
    """The ``checkpoint.pt`` of a finished training folder (contract format).

    A file that is not a weights-only torch checkpoint of that format is an InputError
    naming it (torch's own message is left out: it suggests ``weights_only=False``, which
    would run whatever a pickle in the run folder holds).
    """
    path = Path(train_dir) / "checkpoint.pt"
    if not path.is_file():
        raise MissingInputError(f"no checkpoint.pt in {train_dir}: is that training run finished (DONE)?")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:      # torch raises UnpicklingError, RuntimeError, EOFError, ... for a bad file
        raise _corrupt(path, f"is not a readable weights-only torch checkpoint ({type(e).__name__})") from None
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(ckpt, dict) or k not in ckpt]
    if missing:
        raise _corrupt(path, f"lacks {', '.join(missing)}")
    try:
        ckpt["config"]["train"]["clip_len"], ckpt["model_args"]["image_size"]
    except (KeyError, TypeError):
        raise _corrupt(path, "lacks config.train.clip_len or model_args.image_size") from None
    return ckpt


def load_model(train_dir: Path | str, device: str = "cpu") -> ClipClassifier:
    """The trained model of a training folder, in eval mode on ``device``."""
    return _model_of(load_checkpoint(train_dir), Path(train_dir) / "checkpoint.pt", device)


def _model_of(ckpt: dict, path: Path, device: str) -> ClipClassifier:
    try:
        model = build_model(ckpt["model_name"], **ckpt["model_args"])
        model.load_state_dict(ckpt["model"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise _corrupt(path, f"does not fit its model ({type(e).__name__}: {str(e).splitlines()[0][:200]})") from None
    return model.to(resolve_device(device)).eval()


class ClipFrames:
    """The frames of a clip list at one image size, read once for every model that predicts on them.

    ``clips`` holds the clips that could be read, in order: (clip_id, class_index, uint8 frames (T, size,
    size, 3)), on ``device`` when that is CUDA, else on the CPU. A clip with a missing or unreadable frame or
    meta.json is left out with a warning, which ``warn`` gives again for each later model.
    """

    def __init__(self, clip_dirs: Iterable[Path | str], size: int, device: torch.device | str = "cpu"):
        self.clip_dirs = tuple(map(Path, clip_dirs))
        self.size = size
        keep = torch.device(device) if torch.device(device).type == "cuda" else torch.device("cpu")
        self.clips: list[tuple[str, int, torch.Tensor]] = []
        self.left_out: list[str] = []      # the warning of each clip left out
        for clip_dir in self.clip_dirs:
            try:        # the meta first: reading frames needs it too
                meta = read_meta(clip_dir, "render")
                class_index = int(meta["class_index"])
            except (UserError, KeyError, TypeError, ValueError) as err:
                self.left_out.append(f"clip {clip_dir.name}: {err}{predictions.LEFT_OUT}")
                continue
            try:
                frames = torch.from_numpy(read_frames(clip_dir, size)).to(keep)
            except FrameError as err:
                self.left_out.append(f"{err}{predictions.LEFT_OUT}")
                continue
            self.clips.append((meta.get("clip_id", clip_dir.name), class_index, frames))
        self.warn(stacklevel=3)

    def matches(self, clip_dirs: tuple[Path, ...], size: int) -> bool:
        """Whether these are the frames of ``clip_dirs`` (as paths, in order) at ``size``."""
        return self.clip_dirs == clip_dirs and self.size == size

    def warn(self, stacklevel: int = 2) -> None:
        """Warn of each clip left out (a caller recording warnings per model learns which and why)."""
        for text in self.left_out:
            warnings.warn(text, stacklevel=stacklevel)


@torch.no_grad()
def predict_clips(train_dir: Path | str, clip_dirs: Iterable[Path | str], device: str = "auto",
                  batch_size: int = 32, frames: ClipFrames | None = None) -> pd.DataFrame:
    """One row per sub-sequence: ``clip_id, start, class_index, pred, probs`` (probs: (54,) float32).

    Clips with a missing or unreadable frame or meta.json are reported by a warning and left out.
    ``frames``, when read from the same clips at the model's image size, are used instead of reading them
    (their warnings are the caller's to give).
    """
    ckpt = load_checkpoint(train_dir)
    clip_dirs = tuple(map(Path, clip_dirs))
    size = ckpt["model_args"]["image_size"]
    dev = resolve_device(device)
    if frames is None or not frames.matches(clip_dirs, size):
        frames = ClipFrames(clip_dirs, size, dev)
    return _predict(ckpt, Path(train_dir), frames, dev, batch_size)


def _predict(ckpt: dict, train_dir: Path, frames: ClipFrames, dev: torch.device, batch_size: int) -> pd.DataFrame:
    """``predict_clips`` of a loaded checkpoint on read frames."""
    train_cfg = ckpt["config"]["train"]
    clip_len, stride = train_cfg["clip_len"], train_cfg["clip_stride"]
    model = _model_of(ckpt, train_dir / "checkpoint.pt", str(dev))

    windows: list[tuple[str, int, int]] = []     # (clip_id, start, class_index) of each window predicted
    probs: list[np.ndarray] = []
    pending: list[tuple[tuple[str, int, int], torch.Tensor]] = []

    def flush() -> None:
        if not pending:
            return
        batch = torch.stack([f for _, f in pending])
        probs.append(model.probs(model(to_input(batch, dev))).cpu().numpy().astype(np.float32))
        windows.extend(w for w, _ in pending)
        pending.clear()

    for clip_id, class_index, clip in frames.clips:
        clip = clip.permute(0, 3, 1, 2)
        for start in subsequence_starts(len(clip), clip_len, stride):
            pending.append(((clip_id, start, class_index), clip[start:start + clip_len]))
            if len(pending) == batch_size:
                flush()
    flush()
    ids, starts, labels = zip(*windows) if windows else ((), (), ())
    return predictions.frame(ids, starts, labels,
                             np.concatenate(probs) if probs else np.empty((0, predictions.NUM_CLASSES)))


class CachedPredictor:
    """``predict_clips`` as a ``(train_dir, clip_dirs) -> frame`` predictor that reads a clip list once for
    every model predicting on it in a row (eval: a setting's models on one test variant).

    It keeps the frames of the last (clip list, image size) only, so memory stays flat across clip lists
    (a setting's test clips at 112 px are ~5.2 GB at the `paper` preset's 384 sequences a class). A reused
    list's left-out clips are warned of again.
    """

    def __init__(self, device: str = "auto", batch_size: int = 32):
        self.device = device
        self.batch_size = batch_size
        self._frames: ClipFrames | None = None

    def frames(self, clip_dirs: Iterable[Path | str], size: int) -> ClipFrames:
        """The frames of ``clip_dirs`` at ``size``: the kept ones when they match, else read (and kept)."""
        clip_dirs = tuple(map(Path, clip_dirs))
        if self._frames is not None and self._frames.matches(clip_dirs, size):
            self._frames.warn(stacklevel=3)
            return self._frames
        self._frames = None         # freed before the next list is read
        self._frames = ClipFrames(clip_dirs, size, resolve_device(self.device))
        return self._frames

    @torch.no_grad()
    def __call__(self, train_dir: Path | str, clip_dirs: Iterable[Path | str]) -> pd.DataFrame:
        ckpt = load_checkpoint(train_dir)
        frames = self.frames(clip_dirs, ckpt["model_args"]["image_size"])
        return _predict(ckpt, Path(train_dir), frames, resolve_device(self.device), self.batch_size)


@torch.no_grad()
def predict_windows(train_dir: Path | str, cache: FrameCache, windows, device: torch.device | str,
                    batch_size: int = 256) -> pd.DataFrame:
    """Like ``predict_clips``, on the given windows (``learn.split.part_windows``) of a frame cache held
    on ``device``: the fast path for many models on the same clips."""
    ckpt = load_checkpoint(train_dir)
    tcfg = ckpt["config"]["train"]
    model = load_model(train_dir, str(device))
    data = WindowSet(cache, windows, tcfg["clip_len"], tcfg["clip_stride"], device)
    return data.predict(model, batch_size)
