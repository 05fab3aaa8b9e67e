"""The trained models of a run that eval scores: one per finished train folder of the config's grid."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from clothgap.runs import Run, is_done


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
    return [TrainedModel(setting, variant, model, seed, run.train_dir(setting, variant, model, seed))
            for setting, variant in cfg.pairs() for model in cfg.train.models for seed in cfg.train.seeds]


def finished_models(run: Run) -> list[TrainedModel]:
    """Every train folder of the config's grid that holds a DONE marker."""
    return [m for m in grid_models(run) if is_done(m.folder)]
