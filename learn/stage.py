"""The learn stage's entry point: every (setting, variant, model, seed) of the run's grid."""

from __future__ import annotations

from clothgap.config import pairs
from clothgap.runs import Run, atomic_write_json, is_done
from learn.models import MODEL_NAMES
from learn.train import is_main, train_one


def training_grid(run: Run) -> list[tuple[str, str, str, int]]:
    """(setting, variant, model, seed) in training order: base1 before base2, which freezes its CNN."""
    cfg = run.config.train
    unknown = [m for m in cfg.models if m not in MODEL_NAMES]
    if unknown:
        raise ValueError(f"unknown model(s) {', '.join(unknown)} in train.models; known: {', '.join(MODEL_NAMES)}")
    models = sorted(cfg.models, key=lambda m: (m == "base2", MODEL_NAMES.index(m)))
    return [(setting, variant, model, seed)
            for setting, variant in pairs(run.config)
            for seed in cfg.seeds
            for model in models]


def run_train(run: Run, progress: bool = True) -> dict:
    """Train the whole grid, skipping finished folders; writes and returns ``train/index.json``.

    The index lists every grid entry with its folder (relative to the run) and
    whether it is done, so eval finds results without walking the tree.
    """
    grid = training_grid(run)
    index_path = run.root / "train" / "index.json"

    def write_index() -> dict:
        entries = []
        for setting, variant, model, seed in grid:
            folder = run.train_dir(setting, variant, model, seed)
            entries.append({"setting": setting, "variant": variant, "model": model, "seed": seed,
                            "dir": str(folder.relative_to(run.root)), "done": is_done(folder)})
        index = {"entries": entries}
        if is_main():   # under torchrun, one process writes
            atomic_write_json(index_path, index)
        return index

    for setting, variant, model, seed in grid:
        train_one(run, setting, variant, model, seed, progress)
        write_index()
    return write_index()
