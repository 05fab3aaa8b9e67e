"""Splits are by simulated sequence, stratified by class, written once and shared."""

from __future__ import annotations

import json
from collections import Counter

import pytest

from clothgap.config import ConfigError, StudyConfig
from clothgap.runs import Run, clip_id, mark_done
from learn.config import TrainConfig
from learn.split import get_or_make_split, split_sequences, training_subset


def _labels(classes: int, per_class: int) -> dict[str, int]:
    return {clip_id(i): i % classes for i in range(classes * per_class)}


def test_each_sequence_on_exactly_one_side_and_stratified():
    labels = _labels(54, 12)
    split = split_sequences(labels, val_fraction=0.1, test_fraction=1 / 6, seed=3)
    sides = [set(split[p]) for p in ("train", "val", "test")]
    assert not (sides[0] & sides[1] or sides[0] & sides[2] or sides[1] & sides[2])
    assert set().union(*sides) == set(labels)
    for part, expected in (("test", 2), ("val", 1), ("train", 9)):
        assert Counter(labels[c] for c in split[part]) == {c: expected for c in range(54)}


def test_split_depends_on_seed_only_and_keeps_one_for_training():
    labels = _labels(4, 3)
    assert split_sequences(labels, 0.2, 0.4, seed=1) == split_sequences(dict(reversed(labels.items())), 0.2, 0.4, 1)
    assert split_sequences(labels, 0.2, 0.4, seed=1) != split_sequences(labels, 0.2, 0.4, seed=2)
    tiny = split_sequences(_labels(3, 1), 0.3, 0.6, seed=0)   # one sequence per class: all train
    assert len(tiny["train"]) == 3 and not tiny["val"] and not tiny["test"]
    with pytest.raises(ConfigError, match="val_fraction"):
        split_sequences(labels, 0.5, 0.5, seed=0)


def test_a_training_subset_keeps_every_class_and_nests_in_a_larger_one():
    labels = _labels(54, 8)
    windows = {c: None for c in labels}
    half, quarter = (training_subset(windows, labels, f, seed=5) for f in (0.5, 0.25))
    assert Counter(labels[c] for c in half) == {c: 4 for c in range(54)}
    assert Counter(labels[c] for c in quarter) == {c: 2 for c in range(54)}
    assert set(quarter) < set(half)                                   # the learning curve's points nest
    assert training_subset(windows, labels, 0.5, seed=5) == half      # seeded
    assert set(training_subset(windows, labels, 0.5, seed=6)) != set(half)
    assert Counter(labels[c] for c in training_subset(windows, labels, 0.01, seed=5)) == {c: 1 for c in range(54)}
    assert training_subset(windows, labels, 1.0, seed=5) == windows


def test_get_or_make_split_writes_once_in_contract_format(tmp_path):
    cfg = StudyConfig(train=TrainConfig(val_fraction=0.0, test_fraction=0.25))
    run = Run.create_or_resume(tmp_path / "run", cfg)
    setting = cfg.sim.settings()[0]
    for i, label in _labels(4, 4).items():   # rendered clips only: a run that starts at render
        folder = run.render_dir("paper", setting) / i
        folder.mkdir(parents=True)
        (folder / "meta.json").write_text(json.dumps({"class_index": label}))
        mark_done(folder)
    split = get_or_make_split(run, setting)
    on_disk = json.loads(run.split_path(setting).read_text())
    assert on_disk == split and set(on_disk) == {"by", "seed", "train", "val", "test"}
    assert on_disk["by"] == "sequence" and len(on_disk["test"]) == 4 and on_disk["val"] == []
    before = run.split_path(setting).stat().st_mtime_ns
    assert get_or_make_split(run, setting) == split
    assert run.split_path(setting).stat().st_mtime_ns == before


def test_missing_clips_name_the_command(tmp_path):
    run = Run.create_or_resume(tmp_path / "run", StudyConfig())
    with pytest.raises(ConfigError, match="clothgap sim"):
        get_or_make_split(run, "wind-uniform1")


def test_split_by_subsequence_puts_windows_of_one_sequence_on_both_sides(tmp_path):
    # The paper's protocol (as read): disjoint windows are the items, so one simulation
    # feeds train and test. Windows never share a frame; each window is on one side.
    from learn.split import parse_item, part_clips, part_windows, split_subsequences

    labels = _labels(54, 12)
    split = split_subsequences(labels, num_frames=40, clip_len=10, clip_stride=10, val_fraction=0.1,
                               test_fraction=1 / 6, seed=3)
    items = [i for p in ("train", "val", "test") for i in split[p]]
    assert len(items) == len(set(items)) == 54 * 12 * 4
    assert {parse_item(i)[1] for i in items} == {0, 10, 20, 30}
    shared = set(part_clips(split, "train")) & set(part_clips(split, "test"))
    assert len(shared) > len(part_clips(split, "test")) // 2     # the leak it exists to measure
    windows = part_windows(split, "test")
    assert all(starts and set(starts) <= {0, 10, 20, 30} for starts in windows.values())
    with pytest.raises(ConfigError, match="clip_stride >= clip_len"):
        split_subsequences(labels, 40, 10, 5, 0.1, 0.2, seed=0)
    assert TrainConfig(split_by="subsequence", clip_stride=5).problems()
    assert not TrainConfig(split_by="subsequence", clip_stride=10).problems()
    assert TrainConfig(split_by="frames").problems()


def test_a_split_file_of_the_other_protocol_is_refused(tmp_path):
    cfg = StudyConfig(train=TrainConfig(val_fraction=0.0, test_fraction=0.25))
    run = Run.create_or_resume(tmp_path / "run", cfg)
    setting = cfg.sim.settings()[0]
    run.split_path(setting).parent.mkdir(parents=True, exist_ok=True)
    run.split_path(setting).write_text(json.dumps({"by": "subsequence", "train": [], "val": [], "test": []}))
    with pytest.raises(ConfigError, match="delete it"):
        get_or_make_split(run, setting)


def test_eval_scores_only_the_test_windows_of_a_split_by_subsequence():
    import pandas as pd

    from eval.stage import only_windows

    frame = pd.DataFrame({"clip_id": ["a", "a", "a", "b"], "start": [0, 10, 20, 0], "pred": [1, 2, 3, 4]})
    assert only_windows(frame, {"a": None, "b": None}).equals(frame)
    kept = only_windows(frame, {"a": [10], "b": [0]})
    assert list(zip(kept["clip_id"], kept["start"])) == [("a", 10), ("b", 0)]
