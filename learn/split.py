"""Train/val/test splits, shared by every variant and model of a run.

``train.split_by = "sequence"`` (the default): sub-sequences of one simulated
sequence look almost alike, so splitting by frame or sub-sequence would leak
test material into training. The split lists whole clip ids (one clip = one
simulated sequence), stratified by class.

``train.split_by = "subsequence"``: the paper's protocol as we read Section 7.1
("2,592 sequences ... 2,106 for training, 432 for testing; each sequence
consists of 10 frames", cut from longer simulations): the non-overlapping
``clip_len``-frame windows of every simulated sequence are the items, split at
random per class, so windows of one simulation fall on both sides. It exists to
measure how much that leak is worth (docs/learnability.md); it is not a test of
generalisation. Items are written ``"<clip_id>@<start frame>"``.

Either way the split is written once per setting to ``splits/<setting>.json``:
every render variant and model of the run reads the same file, which keeps the
domain-gap matrix paired.
"""

from __future__ import annotations

import json
from pathlib import Path

from clothgap import seeding
from clothgap.errors import ConfigError, InputError
from clothgap.runs import Run, atomic_write_json, read_meta

PARTS = ("train", "val", "test")


def split_sequences(labels: dict[str, int], val_fraction: float, test_fraction: float,
                    seed: int) -> dict[str, list[str]]:
    """Split clip ids (``{clip_id: class_index}``) per class into train/val/test.

    Each class contributes ``round(n * fraction)`` sequences to val and test and
    keeps at least one for training. The draw depends only on the seed and the
    clip ids, so two settings with the same clips get the same split.
    """
    if not 0 <= val_fraction < 1 or not 0 <= test_fraction < 1 or val_fraction + test_fraction >= 1:
        raise ConfigError(f"val_fraction={val_fraction} and test_fraction={test_fraction} must be in [0, 1) "
                          "and leave something to train on")
    by_class: dict[int, list[str]] = {}
    for cid, label in labels.items():
        by_class.setdefault(int(label), []).append(cid)
    parts: dict[str, list[str]] = {p: [] for p in PARTS}
    for label in sorted(by_class):
        ids = sorted(by_class[label])
        order = seeding.rng(seed, label, seeding.TRAIN, "split").permutation(len(ids))
        ids = [ids[i] for i in order]
        n_test = min(round(len(ids) * test_fraction), len(ids) - 1)
        n_val = min(round(len(ids) * val_fraction), len(ids) - 1 - n_test)
        parts["test"] += ids[:n_test]
        parts["val"] += ids[n_test:n_test + n_val]
        parts["train"] += ids[n_test + n_val:]
    return {p: sorted(ids) for p, ids in parts.items()}


def clip_labels(run: Run, setting: str) -> dict[str, int]:
    """``{clip_id: class_index}`` of the finished clips of a setting.

    Read from the simulated clips when the run has them, otherwise from the
    rendered clips of every configured variant (a run that starts at render).
    """
    folders = [run.sim_dir(setting)] + [run.render_dir(v, setting) for v in run.config.render.variants]
    for folder in folders:
        ids = run.done_clips(folder)
        if ids:
            labels = {}
            for cid in ids:
                meta = read_meta(folder / cid, "sim" if folder == folders[0] else "render")
                if not isinstance(meta.get("class_index"), int):
                    raise InputError(f"{folder / cid / 'meta.json'} has no integer class_index: delete "
                                     f"{folder / cid} and run the stage that made it again")
                labels[cid] = meta["class_index"]
            return labels
    raise ConfigError(f"no finished clips for setting {setting!r} in {', '.join(map(str, folders))}: "
                      f"run `clothgap sim {run.root}` and `clothgap render {run.root}` first")


def window_item(clip_id: str, start: int) -> str:
    return f"{clip_id}@{start}"


def parse_item(item: str) -> tuple[str, int | None]:
    """``"clip"`` -> (clip, None) (every window); ``"clip@30"`` -> (clip, 30) (one window)."""
    clip, sep, start = item.rpartition("@")
    return (clip, int(start)) if sep else (item, None)


def part_windows(split: dict, part: str) -> dict[str, list[int] | None]:
    """``{clip_id: window starts}`` of one part; ``None`` means every window of the clip."""
    out: dict[str, list[int] | None] = {}
    for item in split[part]:
        clip, start = parse_item(item)
        if start is None:
            out[clip] = None
        elif out.get(clip, []) is not None:
            out.setdefault(clip, []).append(start)
    return {c: (sorted(s) if s is not None else None) for c, s in out.items()}


def training_subset(windows: dict[str, list[int] | None], labels: dict[str, int], fraction: float,
                    seed: int) -> dict[str, list[int] | None]:
    """The windows of ``round(n * fraction)`` (at least one) of each class's ``n`` clips in ``windows``, drawn per
    class from ``seed``: a smaller training set with every class, for the data-size learning curve. The draw is
    one permutation per class cut at the fraction, so a smaller fraction's clips are a subset of a larger's."""
    if fraction >= 1:
        return windows
    by_class: dict[int, list[str]] = {}
    for cid in sorted(windows):
        by_class.setdefault(int(labels[cid]), []).append(cid)
    keep: list[str] = []
    for label in sorted(by_class):
        ids = by_class[label]
        order = seeding.rng(seed, label, seeding.TRAIN, "train-subset").permutation(len(ids))
        keep += [ids[i] for i in order[:max(1, round(len(ids) * fraction))]]
    return {cid: windows[cid] for cid in sorted(keep)}


def part_clips(split: dict, part: str) -> list[str]:
    """The clip ids with at least one item in ``part``."""
    return sorted(part_windows(split, part))


def split_subsequences(labels: dict[str, int], num_frames: int, clip_len: int, clip_stride: int,
                       val_fraction: float, test_fraction: float, seed: int) -> dict[str, list[str]]:
    """The paper's protocol: the windows of every sequence (``clip_stride >= clip_len``: no shared
    frame), split per class at random."""
    if clip_stride < clip_len:
        raise ConfigError(f"a split by subsequence needs clip_stride >= clip_len, got {clip_stride} < {clip_len}")
    starts = list(range(0, num_frames - clip_len + 1, clip_stride))
    if not starts:
        raise ConfigError(f"sequences of {num_frames} frames hold no {clip_len}-frame window")
    items = {window_item(cid, s): label for cid, label in labels.items() for s in starts}
    return split_sequences(items, val_fraction, test_fraction, seed)


def get_or_make_split(run: Run, setting: str) -> dict:
    """The run's split of ``setting``: read from ``splits/<setting>.json``, made once if absent."""
    path = run.split_path(setting)
    if path.is_file():
        return load_split(path, run.config.train.split_by)
    split = make_split(run, setting)
    atomic_write_json(path, split)
    return split


def current_split(run: Run, setting: str) -> dict:
    """The split training uses: the saved one, else the one it would make now (not saved, so that a train
    setting changed before training still shapes the split training makes)."""
    path = run.split_path(setting)
    return load_split(path, run.config.train.split_by) if path.is_file() else make_split(run, setting)


def make_split(run: Run, setting: str) -> dict:
    """A split of ``setting``'s simulated clips from the run's train settings and seed (deterministic)."""
    cfg = run.config.train
    labels = clip_labels(run, setting)
    if cfg.split_by == "subsequence":
        parts = split_subsequences(labels, run.config.sim.frames, cfg.clip_len, cfg.clip_stride, cfg.val_fraction,
                                   cfg.test_fraction, run.config.seed)
    else:
        parts = split_sequences(labels, cfg.val_fraction, cfg.test_fraction, run.config.seed)
    return {"by": cfg.split_by, "seed": run.config.seed, **parts}


def load_split(path: Path, by: str = "sequence") -> dict:
    try:
        split = json.loads(Path(path).read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path} is not valid JSON ({e}); delete it to have it remade") from None
    if not isinstance(split, dict):
        raise InputError(f"{path} is not a split; delete it to have it remade")
    missing = [k for k in ("by", *PARTS) if k not in split]
    if missing or split["by"] != by:
        raise ConfigError(f"{path} is not a split by {by} (missing {missing or 'by=' + by}; "
                          f"it says by={split.get('by')!r}); delete it to have it remade")
    return split
