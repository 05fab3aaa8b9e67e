"""Prediction frames: what ``learn.predict.predict_clips`` returns, on disk as CSV.

One row per sub-sequence (``train.clip_len`` frames): ``clip_id, start, class_index, pred`` and the
54 class probabilities, stored as columns ``prob_00 .. prob_53`` so that the CSV
opens in any tool. In memory ``probs`` is an (rows, 54) array beside the frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from clothgap.runs import atomic_write_text
from eval import classes

PROB_COLUMNS = [f"prob_{i:02d}" for i in range(classes.NUM_CLASSES)]
KEY_COLUMNS = ["clip_id", "start", "class_index", "pred"]


def to_flat(frame: pd.DataFrame) -> pd.DataFrame:
    """A predict_clips frame (``probs`` column of 54-vectors) as flat columns."""
    missing = [c for c in KEY_COLUMNS + ["probs"] if c not in frame.columns]
    if missing:
        raise ValueError(f"prediction frame lacks column(s) {', '.join(missing)}; has {', '.join(frame.columns)}")
    probs = np.stack([np.asarray(p, dtype=float) for p in frame["probs"]]) if len(frame) else \
        np.zeros((0, classes.NUM_CLASSES))
    if probs.shape[1] != classes.NUM_CLASSES:
        raise ValueError(f"probs must have {classes.NUM_CLASSES} entries per row, got {probs.shape[1]}")
    flat = frame[KEY_COLUMNS].reset_index(drop=True).copy()
    flat["clip_id"] = flat["clip_id"].astype(str)
    return pd.concat([flat, pd.DataFrame(probs, columns=PROB_COLUMNS)], axis=1)


def save(frame: pd.DataFrame, path: Path) -> None:
    """Write atomically, so a killed eval never leaves a half CSV that a resume would trust."""
    atomic_write_text(path, to_flat(frame).to_csv(index=False, float_format="%.6g"))


def load(path: Path) -> pd.DataFrame:
    """Flat frame (``prob_..`` columns); use ``probs_of`` for the array."""
    frame = pd.read_csv(path, dtype={"clip_id": str})
    missing = [c for c in KEY_COLUMNS + PROB_COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError(f"{path} is not a predictions CSV: lacks {', '.join(missing[:5])}"
                         f"{' ...' if len(missing) > 5 else ''}")
    return frame


def probs_of(frame: pd.DataFrame) -> np.ndarray:
    return frame[PROB_COLUMNS].to_numpy(dtype=float)


def per_sequence(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per clip: true class and the argmax of its mean sub-sequence probabilities.

    This is the video-level decision (the paper classifies test *videos*); the
    sub-sequence rows stay the primary unit because they are what the network sees.
    """
    grouped = frame.groupby("clip_id", sort=True)
    mean_probs = grouped[PROB_COLUMNS].mean()
    out = pd.DataFrame({
        "clip_id": mean_probs.index.astype(str),
        "class_index": grouped["class_index"].first().to_numpy(),
        "pred": mean_probs.to_numpy().argmax(axis=1),
    })
    return pd.concat([out, mean_probs.reset_index(drop=True)], axis=1)


def seed_sequences(frame: pd.DataFrame) -> pd.DataFrame:
    """``per_sequence`` of each seed's rows of a frame of one or several seeds' predictions, stacked."""
    return pd.concat([per_sequence(f) for _, f in frame.groupby("seed")], ignore_index=True)


def sequence_correct(frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Whether each (seed, clip)'s video-level decision (``per_sequence``) is right, and the clip ids to
    resample them by: the per-sequence accuracy of a frame of one or several seeds' predictions."""
    return decisions_correct(seed_sequences(frame))


def decisions_correct(sequences: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """``sequence_correct`` from the frame's ``seed_sequences``."""
    return (sequences["class_index"] == sequences["pred"]).to_numpy(float), sequences["clip_id"].to_numpy()
