"""Training recipes compared on the same data and the same test clips: one lever at a time.

A *recipe* is the run's train settings changed by levers joined with ``+``:
each lever is a name from ``LEVERS`` (``augment``, ``geometry``, ``best``, ...)
or a ``key=value`` train setting, e.g. ``augment+geometry+aux_geometry=0.3``.
Every recipe trains into ``RUN/ablation/<recipe>/<setting>/<variant>/<model>/s<seed>/``
(the train stage's own folders: resumable epoch by epoch, DONE last), is scored
on the setting's test windows (split by sequence unless the run says otherwise)
and compared with the first recipe by a paired bootstrap over test sequences.

Writes ``RUN/eval/ablation-<setting>-<variant>.{json,md}`` (or another name): per recipe and
model, top-1, within one bin, stretching, bending, top-3 with intervals, the
paired difference in top-1 to the first recipe, training time and windows/s,
the kept epoch, and the learning curves (``metrics.csv`` rows). With test variants
(e.g. ``heldout``, rendered for testing only), each recipe is also scored on the same
test clips under each of those looks: what a training lever buys where the look changes.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from clothgap.errors import ConfigError
from clothgap.runs import Run, atomic_write_json, atomic_write_text
from clothgap.settings import apply_overrides, validate
from eval import metrics
from eval import predictions as preds
from learn.config import TrainConfig

# name -> train settings it changes. Adding a lever is one entry here.
LEVERS: dict[str, dict] = {
    "baseline": {},
    "augment": {"augment": True},              # temporal shift, resized crop, flip, colour jitter (on the GPU)
    "camera": {"augment_camera": True},        # a camera's errors per clip: exposure, white balance, vignetting, noise
    "best": {"keep": "best"},                  # early stopping: the epoch of best validation accuracy
    "motion": {"motion": True},                # frame differences beside the frames
    "geometry": {"aux_geometry": 1.0},         # regress the simulated 8 x 8 lattice per frame (training only)
    "bottleneck": {"bottleneck": True},         # classes read only the CNN's predicted lattice (learn.models)
    "factored": {"factored": True},            # extra stretching and bending heads
    "smooth": {"label_smoothing": 0.1},
    "last": {"readout": "last"},               # loss and answer from the last step only
    "narrow": {"width": 32, "fc6": 256, "hidden": 128},
    "decay": {"weight_decay": 0.05},
    "graphs": {"compile": True, "compile_mode": "reduce-overhead"},   # CUDA graphs (speed; rounding only)
    "eager": {"compile": False, "reader_graphs": False},   # no compiling, no graphed readers: against the preset
}


def recipe_config(study: Any, recipe: str) -> TrainConfig:
    """The train settings of ``study`` (a ``clothgap.config.StudyConfig``) changed by the recipe's levers, checked
    like any setting of the run."""
    sets: list[str] = []
    for part in filter(None, recipe.split("+")):
        if "=" in part:
            sets.append(f"train.{part}")
        elif part in LEVERS:
            sets += [f"train.{k}={v}" for k, v in LEVERS[part].items()]
        else:
            raise ConfigError(f"recipe {recipe!r}: unknown lever {part!r}; levers are {', '.join(LEVERS)} "
                              "or a train setting as key=value")
    return validate(apply_overrides(study, sets), where=f"recipe {recipe!r}: ").train


def recipe_root(run: Run, recipe: str) -> Path:
    return run.ablation_dir(recipe)


def _recipe_seeds(cfg: TrainConfig, seeds: list[int] | None) -> list[int]:
    """The seeds a recipe trains: those asked for, else the recipe's own ``train.seeds``."""
    return list(seeds) if seeds is not None else list(cfg.seeds)


def ablation_grid(run: Run, setting: str, variant: str, recipes: list[str], models: list[str] | None = None,
                  seeds: list[int] | None = None) -> list[tuple[str, str, str, int, str]]:
    """The (setting, variant, model, seed, recipe) trainings ``run_ablation`` needs, each model after the one it
    starts from: what ``clothgap.executor.run_train_parallel`` trains side by side before the scoring."""
    from learn.registry import training_order

    grid = []
    for recipe in recipes:
        cfg = recipe_config(run.config, recipe)
        ordered = training_order(models or run.config.train.models, cfg.shared_regressor)
        grid += [(setting, variant, model, seed, recipe) for seed in _recipe_seeds(cfg, seeds) for model in ordered]
    return grid


def _curves(folder: Path) -> list[dict]:
    path = folder / "metrics.csv"
    return json.loads(pd.read_csv(path).to_json(orient="records")) if path.is_file() else []


def training_speed(folder: Path) -> dict:
    """Training seconds (a shared regressor's pass over the windows included) and windows/s (epochs after the
    first, which includes compilation)."""
    curves = _curves(folder)
    config = json.loads((folder / "config.json").read_text())
    windows = config["train_subsequences"]
    steady = [r["seconds"] for r in curves[1:]] or [r["seconds"] for r in curves]
    done = json.loads((folder / "DONE").read_text())
    shape_seconds = done.get("shape_seconds")      # readers on a shared regressor: its pass over their windows
    shapes = {"shape_seconds": shape_seconds} if shape_seconds is not None else {}
    return {"train_seconds": round(sum(r["seconds"] for r in curves) + (shape_seconds or 0.0), 2), **shapes,
            "first_epoch_seconds": round(curves[0]["seconds"], 2) if curves else None,
            "windows_per_s": round(windows / (sum(steady) / len(steady)), 1) if steady else None,
            "train_windows": windows, "kept_epoch": done.get("kept_epoch"),
            "frames_on_device": config.get("frames_on_device"),
            # the last process's set-up (a resumed training's too): split, frame cache, lattices, the windows' frames
            # and lattices onto the device
            "data_seconds": done.get("data_seconds")}


def require_test_clips(run: Run, setting: str) -> dict:
    """The test part of ``setting``'s split (``part_windows``), refused before any training when it is empty: a
    split can hold no test sequence (too few sequences a class for the test share), and then no recipe can be
    scored however long it trains."""
    from learn.split import get_or_make_split, part_windows

    test = part_windows(get_or_make_split(run, setting), "test")
    if not test:
        cfg = run.config
        raise ConfigError(f"the split of {setting} in {run.root} holds no test sequence "
                          f"({cfg.sim.sequences_per_class} sequence(s) a class, train.test_fraction="
                          f"{cfg.train.test_fraction:g}), so no recipe can be scored: raise "
                          "sim.sequences_per_class or train.test_fraction in a new run")
    return test


def run_ablation(run: Run, setting: str, variant: str, recipes: list[str], models: list[str] | None = None,
                 seeds: list[int] | None = None, progress: bool = True, name: str | None = None,
                 test_variants: list[str] | None = None) -> dict:
    """Train and score every recipe x model x seed; write and return the comparison.

    Args:
        run: the run whose rendered clips of ``setting`` / ``variant`` are trained and tested on.
        recipes: recipe names (``recipe_config``); the first is the reference the others are compared with.
        models: default to the run's ``train.models``.
        seeds: default to each recipe's ``train.seeds`` (the run's, unless the recipe sets ``seeds=...``).
        progress: print a line per trained model.
        name: the file stem under ``RUN/eval/`` (default ``ablation-<setting>-<variant>``).
        test_variants: other looks of the same test clips to score every recipe on too (``row["on"]``).

    Returns:
        ``{"json": path of the written report, "top1": {"<recipe>/<model>": accuracy}}``.
    """
    if not recipes:
        raise ConfigError("no recipes given")
    test_variants = [v for v in dict.fromkeys(test_variants or []) if v != variant]
    base = run.config.train
    configs = {r: recipe_config(run.config, r) for r in recipes}
    models = models or list(base.models)
    test = require_test_clips(run, setting)
    for look in test_variants:
        # every test clip, or the look's scores would be of other clips than the training look's
        rendered = set(run.done_clips(run.render_dir(look, setting)))
        missing = sorted(c for c in test if c not in rendered)
        if missing:
            raise ConfigError(f"test variant {look!r} has {len(test) - len(missing)} of the {len(test)} test clips "
                              f"of {setting} rendered ({missing[0]} is missing): render them first "
                              f"(`clothgap render {run.root} --test-variant {look}`)")
    rows, caches = [], {}
    references: dict[str, dict] = {look: {} for look in [variant, *test_variants]}
    out_dir = run.eval_dir
    for recipe in recipes:
        cfg = configs[recipe]
        recipe_seeds = _recipe_seeds(cfg, seeds)
        for model in models:
            frames, folders = _train_and_predict(run, setting, variant, recipe, cfg, model, recipe_seeds, test,
                                                 caches, progress, test_variants)
            row = {"recipe": recipe, "model": model, "seeds": recipe_seeds,
                   "changes": {k: v for k, v in dataclasses.asdict(cfg).items() if getattr(base, k) != v},
                   **_scores(run, frames[variant], model, references[variant], len(rows))}
            if test_variants:
                row["on"] = {look: _scores(run, frames[look], model, references[look], len(rows), stream=k + 1)
                             for k, look in enumerate(test_variants)}
            row["speed"] = [training_speed(f) for f in folders]
            row["curves"] = {f"s{s}": _curves(f) for s, f in zip(recipe_seeds, folders)}
            rows.append(row)
    scored = max((r["sequences"] for r in rows), default=0)
    report = {"run": str(run.root), "setting": setting, "variant": variant, "split_by": base.split_by,
              "test_sequences_in_split": len(test), "test_sequences": scored,
              "base_train": dataclasses.asdict(base), "recipes": rows}
    if test_variants:
        report["test_variants"] = test_variants
    stem = name or f"ablation-{setting}-{variant}"
    atomic_write_json(out_dir / f"{stem}.json", report)
    atomic_write_text(out_dir / f"{stem}.md", markdown(report))
    return {"json": str(out_dir / f"{stem}.json"),
            "top1": {f"{r['recipe']}/{r['model']}": round(r["acc"], 4) for r in rows}}


def _train_and_predict(run: Run, setting: str, variant: str, recipe: str, cfg, model: str, seeds: list[int],
                       test, caches: dict, progress: bool, test_variants: Sequence[str] = ()
                       ) -> tuple[dict[str, pd.DataFrame], list[Path]]:
    """``model`` trained with ``recipe`` for every seed (resumable) and its predictions on the ``test`` windows
    of ``variant`` and of each test variant (kept in each folder's ``test_predictions[-<variant>].csv``): per
    look, all seeds' predictions; and the training folders. ``caches`` holds the frame cache per (look, image
    size), built once."""
    from learn.dataset import build_cache
    from learn.predict import predict_windows
    from learn.train import resolve_device, train_one

    looks = [variant, *test_variants]
    frames: dict[str, list[pd.DataFrame]] = {look: [] for look in looks}
    folders = []
    for seed in seeds:
        t0 = time.perf_counter()
        folder = train_one(run, setting, variant, model, seed, progress, config=cfg, root=recipe_root(run, recipe))
        for look in looks:
            path = folder / ("test_predictions.csv" if look == variant else f"test_predictions-{look}.csv")
            if not path.is_file():
                if (look, cfg.image_size) not in caches:
                    caches[look, cfg.image_size] = build_cache(run, look, setting, cfg.image_size, progress=False)
                preds.save(predict_windows(folder, caches[look, cfg.image_size], test, resolve_device(cfg.device)),
                           path)
            frames[look].append(preds.load(path).assign(seed=seed))
        folders.append(folder)
        if progress:
            print(f"[ablation] {recipe} {model} s{seed}: {time.perf_counter() - t0:.1f} s", flush=True)
    return {look: pd.concat(f, ignore_index=True) for look, f in frames.items()}, folders


def _scores(run: Run, frame: pd.DataFrame, model: str, reference: dict, row_index: int, stream: int = 0) -> dict:
    """Accuracy and its interval of one recipe's ``model`` on the test windows, and for every recipe after the
    first its difference from the first's (``reference``: model -> the first recipe's correct flags and clips).
    ``stream`` > 0: the scores of a test variant, on bootstrap draws of their own."""
    bootstrap = dict(resamples=run.config.eval.bootstrap, confidence=run.config.eval.confidence)
    truth, pred = frame["class_index"].to_numpy(), frame["pred"].to_numpy()
    groups = frame["clip_id"].to_numpy()
    # bootstrap keyed by the row's place (and the test variant's)
    rng = np.random.default_rng([run.config.seed, row_index, stream] if stream else [run.config.seed, row_index])
    scores = metrics.summarize(truth, pred, preds.probs_of(frame), groups, rng=rng, **bootstrap)
    correct = metrics.correct(truth, pred)
    if model in reference:
        ref_correct, ref_groups = reference[model]
        diff = metrics.bootstrap_mean_difference(correct, groups, ref_correct, ref_groups, rng=rng, **bootstrap)
        scores.update(diff.as_dict("acc_minus_first"))
    else:
        reference[model] = (correct, groups)
    # the video-level answer (`eval real`, `clone`): one decision per (seed, sequence) from its windows' mean
    # probabilities (drawn after the scores above, whose intervals stay what they were)
    scores.update(metrics.bootstrap_mean(*preds.sequence_correct(frame), rng=rng, **bootstrap).as_dict("seq_acc"))
    return scores


def _pct(row: dict, key: str) -> str:
    if key not in row or row[key] is None or math.isnan(row[key]):
        return "-"
    return f"{100 * row[key]:.1f} [{100 * row[key + '_lo']:.1f}, {100 * row[key + '_hi']:.1f}]"


def markdown(report: dict) -> str:
    lines = [f"# Training recipes on {report['setting']} / {report['variant']}",
             "",
             f"Run `{report['run']}`, split by {report['split_by']}, {report['test_sequences']} test sequences scored "
             f"(of {report['test_sequences_in_split']} in the split; the others were not rendered); "
             "intervals: 95 % bootstrap over test sequences; the difference is paired with the first recipe.",
             "",
             "| recipe | model | top-1 % | per sequence % | within one bin % | stretching % | bending % | top-3 % | "
             "top-1 minus first (points) | windows/s | kept epoch |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in report["recipes"]:
        speed = r["speed"][0] if r["speed"] else {}
        lines.append(f"| {r['recipe']} | {r['model']} | {_pct(r, 'acc')} | {_pct(r, 'seq_acc')} | {_pct(r, 'within1')} | "
                     f"{_pct(r, 'stretch_acc')} | {_pct(r, 'bend_acc')} | {_pct(r, 'top3')} | "
                     f"{_pct(r, 'acc_minus_first')} | {speed.get('windows_per_s', '-')} | "
                     f"{speed.get('kept_epoch', '-')} |")
    for look in report.get("test_variants", []):
        lines += ["", f"On the same test clips rendered as `{look}` (a look the recipes did not train on):", "",
                  "| recipe | model | top-1 % | within one bin % | stretching % | bending % | top-1 minus first (points) |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for r in report["recipes"]:
            o = r["on"][look]
            lines.append(f"| {r['recipe']} | {r['model']} | {_pct(o, 'acc')} | {_pct(o, 'within1')} | "
                         f"{_pct(o, 'stretch_acc')} | {_pct(o, 'bend_acc')} | {_pct(o, 'acc_minus_first')} |")
    return "\n".join(lines) + "\n"
