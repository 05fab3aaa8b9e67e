"""learn.predict on tiny trained models: the caching predictor reads a clip list once for every model and
predicts what ``predict_clips`` predicts, with the same warnings for the clips it leaves out."""

from __future__ import annotations

import shutil
import warnings
from collections import Counter

import numpy as np
import pandas as pd
import pytest

import learn.predict
from eval.stage import _left_out_reason
from learn.predict import CachedPredictor, ClipFrames, predict_clips
from learn.synthetic import synthetic_run
from learn.train import train_one
from tests.conftest import SETTING, VARIANT, tiny_train_config


@pytest.fixture(scope="module")
def two_models(tmp_path_factory):
    """Two seeds of a tiny lrcn trained for one epoch, and the run's rendered clips they predict on."""
    run = synthetic_run(tmp_path_factory.mktemp("predict") / "run",
                        tiny_train_config(epochs=1, models=("lrcn",), seeds=(0, 1)))
    dirs = [train_one(run, SETTING, VARIANT, "lrcn", s, progress=False) for s in (0, 1)]
    clips = sorted(p for p in run.render_dir(VARIANT, SETTING).iterdir() if p.is_dir())
    return dirs, clips


def count_reads(monkeypatch) -> Counter:
    """Count ``learn.predict``'s frame reads per clip folder name."""
    reads: Counter = Counter()
    read = learn.predict.read_frames

    def counted(clip_dir, size, *args, **kwargs):
        reads[clip_dir.name] += 1
        return read(clip_dir, size, *args, **kwargs)

    monkeypatch.setattr(learn.predict, "read_frames", counted)
    return reads


def assert_same_predictions(got: pd.DataFrame, want: pd.DataFrame) -> None:
    pd.testing.assert_frame_equal(got.drop(columns="probs"), want.drop(columns="probs"))
    np.testing.assert_array_equal(np.stack(got["probs"]), np.stack(want["probs"]))


def predict_recording(predictor, train_dir, clips) -> tuple[pd.DataFrame, list[str]]:
    """A predictor's frame and the warnings it gave, as eval.stage records them."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frame = predictor(train_dir, clips)
    return frame, [str(w.message) for w in caught]


def test_cached_predictor_reads_each_clip_once_for_two_models_and_predicts_as_predict_clips(two_models, monkeypatch):
    dirs, clips = two_models
    want = [predict_clips(d, clips, device="cpu") for d in dirs]
    assert not np.array_equal(np.stack(want[0]["probs"]), np.stack(want[1]["probs"]))  # two different models

    reads = count_reads(monkeypatch)
    cached = CachedPredictor(device="cpu")
    got = [cached(d, clips) for d in dirs]
    assert reads == Counter({c.name: 1 for c in clips})
    for g, w in zip(got, want):
        assert_same_predictions(g, w)
    assert len(got[0]) == len(clips) * 3

    # One clip list kept at a time: another list is read, and the first one again after it.
    assert_same_predictions(cached(dirs[1], clips[:2]), want[1][want[1]["clip_id"].isin([c.name for c in clips[:2]])]
                            .reset_index(drop=True))
    cached(dirs[0], clips)
    assert reads == Counter({c.name: 3 if c in clips[:2] else 2 for c in clips})

    # predict_clips takes frames read for it, and reads its own when they are of another size or clip list.
    frames, fewer, smaller = ClipFrames(clips, 32), ClipFrames(clips[:1], 32), ClipFrames(clips[:1], 16)
    reads.clear()
    assert_same_predictions(predict_clips(dirs[0], clips, device="cpu", frames=frames), want[0])
    assert not reads
    predict_clips(dirs[0], clips, device="cpu", frames=fewer)
    predict_clips(dirs[0], clips[:1], device="cpu", frames=smaller)
    assert reads == Counter({c.name: 2 if c == clips[0] else 1 for c in clips})


def test_a_corrupt_clip_is_left_out_with_the_same_warning_for_each_model_on_reused_frames(two_models, tmp_path,
                                                                                          monkeypatch):
    dirs, clips = two_models
    good, bad_frame, no_meta = (shutil.copytree(c, tmp_path / c.name) for c in clips[:3])
    (bad_frame / "ldr" / "0003.png").write_bytes(b"not a png")
    (no_meta / "meta.json").unlink()
    mine = [good, bad_frame, no_meta]

    want = [predict_recording(lambda d, c: predict_clips(d, c, device="cpu"), d, mine) for d in dirs]
    reads = count_reads(monkeypatch)
    cached = CachedPredictor(device="cpu")
    got = [predict_recording(cached, d, mine) for d in dirs]
    assert reads == Counter({good.name: 1, bad_frame.name: 1})     # no meta: its frames are never read

    for (frame, caught), (want_frame, want_caught) in zip(got, want):
        assert_same_predictions(frame, want_frame)
        assert set(frame["clip_id"]) == {good.name}
        assert caught == want_caught and len(caught) == 2
        assert all(text.endswith("; clip left out of the predictions") for text in caught)
        records = [warnings.WarningMessage(text, UserWarning, "", 0) for text in caught]
        assert "0003.png" in _left_out_reason(bad_frame, records)
        assert "meta.json is missing" in _left_out_reason(no_meta, records)
