"""The trained models of a run that eval scores: one per finished train folder of the config's grid."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from clothgap.runs import Run, is_done
from learn.registry import training_grid


@dataclass(frozen=True)
class TrainedModel:
    setting: str
    variant: str
    model: str
    seed: int
    folder: Path

    @property
    def checkpoint(self) -> Path:
        return self.folder / "checkpoint.pt"


def grid_models(run: Run) -> list[TrainedModel]:
    """Every (setting, variant, model, seed) of the config's grid with its train folder, finished or not."""
    cfg = run.config
    pairs, models, seeds = cfg.pairs(), list(cfg.train.models), list(cfg.train.seeds)
    # The tables list a (setting, variant)'s models in the config's order, each with its seeds.
    grid = sorted(training_grid(cfg), key=lambda g: (pairs.index(g[:2]), models.index(g[2]), seeds.index(g[3])))
    return [TrainedModel(setting, variant, model, seed, run.train_dir(setting, variant, model, seed))
            for setting, variant, model, seed in grid]


def finished_models(run: Run) -> list[TrainedModel]:
    """Every train folder of the config's grid that holds a DONE marker."""
    return [m for m in grid_models(run) if is_done(m.folder)]
