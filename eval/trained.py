"""The trained models of a run that eval scores: one per finished train folder of the config's grid."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from clothgap.config import pairs
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


def finished_models(run: Run) -> list[TrainedModel]:
    """Every train folder of the config's grid that holds a DONE marker."""
    cfg = run.config
    found = []
    for setting, variant in pairs(cfg):
        for model in cfg.train.models:
            for seed in cfg.train.seeds:
                folder = run.train_dir(setting, variant, model, seed)
                if is_done(folder):
                    found.append(TrainedModel(setting, variant, model, seed, folder))
    return found
