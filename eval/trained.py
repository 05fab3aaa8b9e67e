"""The trained models of a run that eval scores: one per finished train folder of the config's grid."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from clothgap.errors import MissingInputError
from clothgap.runs import Run, file_sha256, is_done
from learn.registry import training_grid


@dataclass(frozen=True)
class TrainedModel:
    setting: str
    variant: str
    model: str
    seed: int
    folder: Path
    recipe: str = ""        # an ``eval.ablation`` recipe's model (``RUN/ablation/<recipe>/...``), else the run's own

    @property
    def checkpoint(self) -> Path:
        return self.folder / "checkpoint.pt"


def checkpoint_sha256(m: TrainedModel) -> str:
    """sha256 of a finished model's checkpoint.pt (cached per file state), or a MissingInputError."""
    if not m.checkpoint.is_file():
        raise MissingInputError(f"{m.folder} is marked DONE but holds no checkpoint.pt: delete that folder and "
                                f"run `clothgap train` again")
    return file_sha256(m.checkpoint)


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
