"""The models the learn stage can train, one entry each (no torch here: config checks and ``--help`` read it).

An entry says how ``learn.models.build_model`` assembles the model from its
parts (the per-frame CNN, an optional recurrent layer, the heads) and which
other model must be trained first. Adding a model is one entry here; a
building block the entries do not offer yet goes into ``learn.models``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class ModelEntry:
    """One registered model: its name, what it is, and how it is built."""

    name: str
    description: str
    title: str                      # its column title in the tables and the report (the paper's Table 3)
    temporal: str | None            # the recurrent layer over frames: "lstm", "rnn", or None (per frame)
    freeze_cnn: bool = False        # the CNN's weights come from ``needs`` and stay fixed
    readout: str | None = None      # a readout the model always uses, whatever train.readout says
    needs: str | None = None        # a model whose trained checkpoint this one starts from (trained first)


MODELS: dict[str, ModelEntry] = {e.name: e for e in (
    ModelEntry("lrcn", "AlexNet-style CNN + fc6 per frame, an LSTM over the frames (the paper's Section 5)",
               "CNN+LSTM (RGB-V)", temporal="lstm"),
    # A per-frame classifier: its answer is always the clip average.
    ModelEntry("base1", "the CNN + fc6 alone, one prediction per frame, averaged over the clip",
               "Base-1 (CNN, RGB-I)", temporal=None, readout="mean"),
    ModelEntry("base2", "base1's CNN frozen (its weights put in by the trainer), an LSTM trained on top",
               "Base-2 (fixed CNN+LSTM, RGB-V)", temporal="lstm", freeze_cnn=True, needs="base1"),
    ModelEntry("base3", "lrcn with a vanilla (tanh) RNN instead of the LSTM", "Base-3 (CNN+RNN, RGB-V)",
               temporal="rnn"),
)}
MODEL_NAMES = tuple(MODELS)


def get_model_entry(name: str) -> ModelEntry:
    """The entry called ``name``; an unknown name is an error listing the known ones."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; known models: {', '.join(MODEL_NAMES)}")
    return MODELS[name]


def model_needs(name: str, shared_regressor: str = "") -> str | None:
    """The model whose trained checkpoint ``name`` starts from: its entry's ``needs``, or, with
    ``train.shared_regressor`` naming a model, that model for every other one (whose readers then read its
    frozen CNN's lattice, ``learn.train``)."""
    if reads_shared_regressor(shared_regressor, name):
        return shared_regressor
    return get_model_entry(name).needs


def reads_shared_regressor(shared_regressor: str, model_name: str) -> bool:
    """Whether ``model_name`` trains its readers alone on another model's frozen regressor
    (``train.shared_regressor``)."""
    return bool(shared_regressor) and model_name != shared_regressor


def _depth(name: str, shared_regressor: str = "") -> int:
    """How many models must be trained before ``name`` (the length of its ``needs`` chain)."""
    needs = model_needs(name, shared_regressor)
    return 0 if needs is None else 1 + _depth(needs, shared_regressor)


def training_order(names: Iterable[str], shared_regressor: str = "") -> list[str]:
    """``names`` sorted so that every model comes after the model it needs, else in registry order."""
    return sorted(names, key=lambda m: (_depth(m, shared_regressor), MODEL_NAMES.index(m)))


def training_grid(cfg, settings: Iterable[str] | None = None, variants: Iterable[str] | None = None,
                  models: Iterable[str] | None = None, seeds: Iterable[int] | None = None
                  ) -> list[tuple[str, str, str, int]]:
    """The run's one (setting, variant, model, seed) grid, in training order: by (setting, variant) as
    ``cfg.pairs()`` gives them, then seed, then each model after the model it needs. ``settings``,
    ``variants``, ``models``, ``seeds`` keep only those (None: all the config has)."""
    def kept(values, wanted) -> list:
        wanted = None if wanted is None else set(wanted)
        return [v for v in values if wanted is None or v in wanted]

    settings_kept, variants_kept = set(kept(cfg.sim.settings(), settings)), set(kept(cfg.render.variants, variants))
    seeds_kept = kept(cfg.train.seeds, seeds)
    models_kept = training_order(kept(cfg.train.models, models), cfg.train.shared_regressor)
    return [(setting, variant, model, seed)
            for setting, variant in cfg.pairs() if setting in settings_kept and variant in variants_kept
            for seed in seeds_kept
            for model in models_kept]


def describe_models() -> str:
    """A human-readable list (for ``clothgap train --list-models``): name, description, what it needs."""
    lines = []
    for entry in MODELS.values():
        needs = f" (trains {entry.needs} first)" if entry.needs else ""
        lines.append(f"{entry.name}: {entry.description}{needs}")
    return "\n".join(lines)
