"""Prediction frames and their CSV: one row per window (``train.clip_len`` frames of a clip).

In memory a frame has ``clip_id, start, class_index, pred`` and ``probs`` (a 54-vector per row); on disk the
probabilities are columns ``prob_00 .. prob_53`` so that the CSV opens in any tool. Training writes its
kept model's ``val_predictions.csv`` this way (recipes, ensembles of seeds, are then compared on validation
windows after the fact), eval its test predictions (``eval.predictions`` reads them). No torch here: eval's
tables and report read predictions without it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from clothgap.runs import atomic_write_text
from sim.classes import NUM_CLASSES

# Ends the warning for a clip a prediction leaves out; eval.stage reads the reason before it.
LEFT_OUT = "; clip left out of the predictions"

PROB_COLUMNS = [f"prob_{i:02d}" for i in range(NUM_CLASSES)]
KEY_COLUMNS = ["clip_id", "start", "class_index", "pred"]


def frame(clip_ids, starts, class_index, probs: np.ndarray) -> pd.DataFrame:
    """A prediction frame from its windows and their (windows, 54) class probabilities."""
    probs = np.asarray(probs, np.float32).reshape(-1, NUM_CLASSES)
    return pd.DataFrame({"clip_id": list(clip_ids), "start": np.asarray(starts), "class_index": np.asarray(class_index),
                         "pred": probs.argmax(1), "probs": list(probs)})


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
