"""Prediction frames and their CSV: one row per window (``train.clip_len`` frames of a clip).

In memory a frame has ``clip_id, start, class_index, pred`` and ``probs`` (a 54-vector per row); on disk the
probabilities are columns ``prob_00 .. prob_53`` so that the CSV opens in any tool. Training writes its
kept model's ``val_predictions.csv`` this way (recipes, ensembles of seeds, are then compared on validation
windows after the fact), eval its test predictions (``eval.predictions`` reads them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from clothgap.runs import atomic_write_text
from learn.models import NUM_CLASSES, ClipClassifier
from learn.windows import WindowSet

PROB_COLUMNS = [f"prob_{i:02d}" for i in range(NUM_CLASSES)]
KEY_COLUMNS = ["clip_id", "start", "class_index", "pred"]


def to_flat(frame: pd.DataFrame) -> pd.DataFrame:
    """A prediction frame (``probs`` column of 54-vectors) as flat columns."""
    missing = [c for c in KEY_COLUMNS + ["probs"] if c not in frame.columns]
    if missing:
        raise ValueError(f"prediction frame lacks column(s) {', '.join(missing)}; has {', '.join(frame.columns)}")
    probs = np.stack([np.asarray(p, dtype=float) for p in frame["probs"]]) if len(frame) else \
        np.zeros((0, NUM_CLASSES))
    if probs.shape[1] != NUM_CLASSES:
        raise ValueError(f"probs must have {NUM_CLASSES} entries per row, got {probs.shape[1]}")
    flat = frame[KEY_COLUMNS].reset_index(drop=True).copy()
    flat["clip_id"] = flat["clip_id"].astype(str)
    return pd.concat([flat, pd.DataFrame(probs, columns=PROB_COLUMNS)], axis=1)


def save(frame: pd.DataFrame, path: Path) -> None:
    """Write atomically, so a killed run never leaves a half CSV that a resume would trust."""
    atomic_write_text(path, to_flat(frame).to_csv(index=False, float_format="%.6g"))


@torch.no_grad()
def window_predictions(model: ClipClassifier, data: WindowSet, batch_size: int = 256,
                       amp: bool | None = None) -> pd.DataFrame:
    """``model``'s prediction frame on every window of ``data`` (no augmentation), in eval mode."""
    model.eval()
    amp = data.device.type == "cuda" if amp is None else amp
    probs = []
    with torch.autocast(data.device.type, dtype=torch.bfloat16, enabled=amp):
        for x, _, _ in data.batches(batch_size):
            probs.append(model.probs(model(x)).float().cpu().numpy())
    p = np.concatenate(probs) if probs else np.zeros((0, NUM_CLASSES), np.float32)
    return pd.DataFrame({"clip_id": data.clip_ids, "start": data.starts.numpy(),
                         "class_index": data.labels.numpy(), "pred": p.argmax(1) if len(p) else [],
                         "probs": list(p.astype(np.float32))})
