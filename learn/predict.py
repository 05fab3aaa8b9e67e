"""Predictions of a trained model on rendered clips of any variant (for eval).

Frames are read straight from the clip folders (no cache), resized to the
model's image size, and cut into the sub-sequences the model was trained on
(``clip_len`` frames every ``clip_stride``, no augmentation).
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
from learn.dataset import FrameCache, FrameError, read_frames, subsequence_starts, to_input
from learn.models import ClipClassifier, build_model
from learn import predictions
from learn.train import resolve_device
from learn.windows import WindowSet


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
    ckpt = load_checkpoint(train_dir)
    path = Path(train_dir) / "checkpoint.pt"
    try:
        model = build_model(ckpt["model_name"], **ckpt["model_args"])
        model.load_state_dict(ckpt["model"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise _corrupt(path, f"does not fit its model ({type(e).__name__}: {str(e).splitlines()[0][:200]})") from None
    return model.to(resolve_device(device)).eval()


@torch.no_grad()
def predict_clips(train_dir: Path | str, clip_dirs: Iterable[Path | str], device: str = "auto",
                  batch_size: int = 32) -> pd.DataFrame:
    """One row per sub-sequence: ``clip_id, start, class_index, pred, probs`` (probs: (54,) float32).

    Clips with a missing or unreadable frame or meta.json are reported by a warning and left out.
    """
    ckpt = load_checkpoint(train_dir)
    train_cfg = ckpt["config"]["train"]
    size, clip_len, stride = ckpt["model_args"]["image_size"], train_cfg["clip_len"], train_cfg["clip_stride"]
    dev = resolve_device(device)
    model = load_model(train_dir, str(dev))

    windows: list[tuple[str, int, int]] = []     # (clip_id, start, class_index) of each window predicted
    probs: list[np.ndarray] = []
    pending: list[tuple[tuple[str, int, int], torch.Tensor]] = []

    def flush() -> None:
        if not pending:
            return
        frames = torch.stack([f for _, f in pending])
        probs.append(model.probs(model(to_input(frames, dev))).cpu().numpy().astype(np.float32))
        windows.extend(w for w, _ in pending)
        pending.clear()

    for clip_dir in map(Path, clip_dirs):
        try:        # the meta first: reading frames needs it too
            meta = read_meta(clip_dir, "render")
            class_index = int(meta["class_index"])
        except (UserError, KeyError, TypeError, ValueError) as err:
            warnings.warn(f"clip {clip_dir.name}: {err}; clip left out of the predictions", stacklevel=2)
            continue
        try:
            frames = torch.from_numpy(read_frames(clip_dir, size)).permute(0, 3, 1, 2)
        except FrameError as err:
            warnings.warn(f"{err}; clip left out of the predictions", stacklevel=2)
            continue
        for start in subsequence_starts(len(frames), clip_len, stride):
            pending.append(((meta.get("clip_id", clip_dir.name), start, class_index),
                            frames[start:start + clip_len]))
            if len(pending) == batch_size:
                flush()
    flush()
    ids, starts, labels = zip(*windows) if windows else ((), (), ())
    return predictions.frame(ids, starts, labels,
                             np.concatenate(probs) if probs else np.empty((0, predictions.NUM_CLASSES)))


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
