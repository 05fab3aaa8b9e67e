"""Prediction frames: what ``learn.predict.predict_clips`` returns, on disk as CSV (the format is
``learn.predictions``'s: ``clip_id, start, class_index, pred`` and ``prob_00 .. prob_53``), read back and
summarised per sequence.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from learn import predictions as _format

# The format is learn's (training writes validation predictions in it); eval's modules know it by these names.
KEY_COLUMNS, PROB_COLUMNS = _format.KEY_COLUMNS, _format.PROB_COLUMNS
to_flat, save = _format.to_flat, _format.save


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


def seed_average(frame: pd.DataFrame) -> pd.DataFrame:
    """The seeds of a stacked frame (a ``seed`` column) as one model: one row per window that every seed
    scored (sorted by clip and start), the seeds' class probabilities averaged, the most probable class its
    ``pred``."""
    seeds = frame["seed"].nunique()
    everyone = frame.groupby(["clip_id", "start"])["seed"].transform("nunique") == seeds
    mean = (frame[everyone].groupby(["clip_id", "start"], sort=True)
            .agg({"class_index": "first", **{c: "mean" for c in PROB_COLUMNS}}).reset_index())
    mean["pred"] = mean[PROB_COLUMNS].to_numpy().argmax(axis=1)
    return mean[KEY_COLUMNS + PROB_COLUMNS]


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
