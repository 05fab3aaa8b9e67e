"""Predictions of a trained model on rendered clips of any variant (for eval).

Frames are read straight from the clip folders (no cache), resized to the
model's image size, and cut into the sub-sequences the model was trained on
(``clip_len`` frames every ``clip_stride``, no augmentation).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd
import torch

from clothgap.errors import MissingInputError
from learn.dataset import FrameError, read_frames, subsequence_starts, to_input
from learn.models import ClipClassifier, build_model
from learn.train import resolve_device


def load_checkpoint(train_dir: Path | str) -> dict:
    """The ``checkpoint.pt`` of a finished training folder (contract format)."""
    path = Path(train_dir) / "checkpoint.pt"
    if not path.is_file():
        raise MissingInputError(f"no checkpoint.pt in {train_dir}: is that training run finished (DONE)?")
    return torch.load(path, map_location="cpu", weights_only=True)


def load_model(train_dir: Path | str, device: str = "cpu") -> ClipClassifier:
    """The trained model of a training folder, in eval mode on ``device``."""
    ckpt = load_checkpoint(train_dir)
    model = build_model(ckpt["model_name"], **ckpt["model_args"])
    model.load_state_dict(ckpt["model"])
    return model.to(resolve_device(device)).eval()


@torch.no_grad()
def predict_clips(train_dir: Path | str, clip_dirs: Iterable[Path | str], device: str = "auto",
                  batch_size: int = 32) -> pd.DataFrame:
    """One row per sub-sequence: ``clip_id, start, class_index, pred, probs`` (probs: (54,) float32).

    Clips with a missing or unreadable frame are reported by a warning and left out.
    """
    ckpt = load_checkpoint(train_dir)
    train_cfg = ckpt["config"]["train"]
    size, clip_len, stride = ckpt["model_args"]["image_size"], train_cfg["clip_len"], train_cfg["clip_stride"]
    dev = resolve_device(device)
    model = load_model(train_dir, str(dev))

    rows: list[dict] = []
    pending: list[tuple[dict, torch.Tensor]] = []

    def flush() -> None:
        if not pending:
            return
        frames = torch.stack([f for _, f in pending])
        probs = model.probs(model(to_input(frames, dev))).cpu().numpy().astype(np.float32)
        for (row, _), p in zip(pending, probs):
            rows.append({**row, "pred": int(p.argmax()), "probs": p})
        pending.clear()

    for clip_dir in map(Path, clip_dirs):
        try:
            frames = torch.from_numpy(read_frames(clip_dir, size)).permute(0, 3, 1, 2)
        except FrameError as err:
            warnings.warn(f"{err}; clip left out of the predictions", stacklevel=2)
            continue
        meta = json.loads((clip_dir / "meta.json").read_text())
        for start in subsequence_starts(len(frames), clip_len, stride):
            pending.append(({"clip_id": meta.get("clip_id", clip_dir.name), "start": start,
                             "class_index": int(meta["class_index"])}, frames[start:start + clip_len]))
            if len(pending) == batch_size:
                flush()
    flush()
    return pd.DataFrame(rows, columns=["clip_id", "start", "class_index", "pred", "probs"])
