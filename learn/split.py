"""Train/val/test splits by simulated sequence, shared by every variant and model.

Sub-sequences of one simulated sequence look almost alike, so splitting by frame
or sub-sequence would leak test material into training. A split therefore lists
whole clip ids (one clip = one simulated sequence), is stratified by class, and
is written once per setting to ``splits/<setting>.json``: every render variant
and model of the run reads the same file, which keeps the domain-gap matrix
paired.
"""

from __future__ import annotations

import json
from pathlib import Path

from clothgap import seeding
from clothgap.config import ConfigError
from clothgap.runs import Run, atomic_write_json

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
            return {cid: int(json.loads((folder / cid / "meta.json").read_text())["class_index"]) for cid in ids}
    raise ConfigError(f"no finished clips for setting {setting!r} in {', '.join(map(str, folders))}: "
                      f"run `clothgap sim {run.root}` and `clothgap render {run.root}` first")


def get_or_make_split(run: Run, setting: str) -> dict:
    """The run's split of ``setting``: read from ``splits/<setting>.json``, made once if absent."""
    path = run.split_path(setting)
    if path.is_file():
        return load_split(path)
    cfg = run.config.train
    parts = split_sequences(clip_labels(run, setting), cfg.val_fraction, cfg.test_fraction, run.config.seed)
    split = {"by": "sequence", "seed": run.config.seed, **parts}
    atomic_write_json(path, split)
    return split


def load_split(path: Path) -> dict:
    split = json.loads(Path(path).read_text())
    missing = [k for k in ("by", *PARTS) if k not in split]
    if missing or split["by"] != "sequence":
        raise ConfigError(f"{path} is not a split by sequence (missing {missing or 'by=sequence'}); "
                          "delete it to have it remade")
    return split
