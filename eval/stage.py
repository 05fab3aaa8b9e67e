"""The eval stage: every finished model on every rendered test variant, then the tables.

``run_eval(run)`` reads only what earlier stages wrote (contracts in
docs/contracts.md) and writes under ``run.eval_dir``::

    predictions/<setting>/<train_variant>/<model>/s<seed>/<test_variant>.csv
                           one row per test sub-sequence (train.clip_len frames) (resumable: kept if present)
    results.csv            one row per (setting, train variant, model, test variant), seeds pooled
    table3.csv, table3.md  the paper's Table 3 shape (in-domain rows)
    domain_gap.csv         every (train, test) variant pair: accuracy, drop, gap, intervals
    axis_ranking.csv       render axes ranked by how much of the gap each closes (>1 variant)
    figures/confusion/<setting>/<train_variant>/<model>/<test_variant>.png
    figures/gap/<setting>/<model>.png
    summary.json
    measured.csv, measured_correlations.csv, measured.md, measured.json, measured/...
                           the measured-fabric set (eval.measured), when eval.measured_sequences > 0

and, when ``eval.sim_analysis`` names them, the sim stage's Table 2 / sensitivity
analyses into ``RUN/sim_analysis/``.

Test variants are all variants rendered for a setting (``render/*/<setting>``),
not only those in the config, so a held-out variant rendered later is picked up.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import pandas as pd

from clothgap import seeding
from clothgap.errors import ConfigError, InputError, UserError
from clothgap.parallel import chunk_size, pool_size, spawn_pool
from clothgap.runs import Run, atomic_write_json, atomic_write_text, file_sha256, is_done, read_meta
from clothgap.settings import to_dict
from eval import figures, metrics, tables
from eval import predictions as preds
from eval.trained import TrainedModel, checkpoint_sha256, finished_models
from learn.predictions import LEFT_OUT
from sim.phases import timed

# (train_dir, clip_dirs) -> predict_clips-shaped frame; the default is learn.predict.CachedPredictor.
Predictor = Callable[[Path, list[Path]], pd.DataFrame]

# Keys of a rendered clip's ``render`` meta that are per-clip draws, seeds or quality, not
# appearance settings that variants compare (used when the render registry cannot say).
_NOT_AXES = {"resolution", "spp", "backend", "write_hdr", "name", "description", "draws", "clip_index",
             "seed_streams", "sampler_seed", "run_seed", "seed", "seeds"}


def _default_predictor() -> Predictor:
    """``learn.predict.predict_clips`` reading each test variant's frames once for a setting's models."""
    from learn.predict import CachedPredictor

    return CachedPredictor()


def rendered_variants(run: Run, setting: str) -> list[str]:
    """Variants with at least one finished clip of ``setting`` (configured ones first)."""
    root = run.render_root
    names = sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    names = [n for n in names if run.done_clips(run.render_dir(n, setting))]
    configured = [v for v in run.config.render.variants if v in names]
    return configured + [n for n in names if n not in configured]


def test_windows(run: Run, setting: str) -> dict[str, list[int] | None]:
    """``{clip_id: test window starts, or None for every window}`` of the setting's split."""
    from learn.split import part_windows

    path = run.split_path(setting)
    if not path.is_file():
        raise ConfigError(f"no split {path}: run `clothgap train {run.root}` first (it writes the splits)")
    try:
        split = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path} is not valid JSON ({e}): delete it and run `clothgap train {run.root}` "
                         "to have the split made again") from None
    if not isinstance(split, dict) or "test" not in split:
        raise ConfigError(f"{path} has no 'test' list of clip ids")
    return part_windows(split, "test")


def test_clips(run: Run, setting: str) -> list[str]:
    return sorted(test_windows(run, setting))


def only_windows(frame: pd.DataFrame, windows: dict[str, list[int] | None]) -> pd.DataFrame:
    """The rows of a prediction frame whose (clip_id, start) is a test item (a split by sub-sequence)."""
    if all(w is None for w in windows.values()):
        return frame
    keep = [windows.get(c) is None or s in windows[c] for c, s in zip(frame["clip_id"], frame["start"])]
    return frame[keep].reset_index(drop=True)


def _flatten(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def _axis_names() -> set[str] | None:
    """The appearance settings a render variant defines (None when render.variants is unavailable)."""
    try:
        from render.variants import RenderVariant
    except ImportError:
        return None
    return set(RenderVariant().settings())


def variant_settings(run: Run, variant: str) -> dict:
    """The appearance settings a variant was rendered with, flattened, from a rendered meta.json.

    Only the variant's own settings count as axes: per-clip draws, seeds and
    quality (spp, resolution) are in the same meta but are not what variants
    compare. Falls back to the render registry when no rendered clip says.
    """
    allowed = _axis_names()
    for setting in run.config.sim.settings():
        folder = run.render_dir(variant, setting)
        for clip in run.done_clips(folder):
            try:
                meta = read_meta(folder / clip, "render")
            except UserError:       # a damaged clip is reported as left out by predict_all; ask the next one
                continue
            render = meta.get("render")
            if isinstance(render, dict):
                if allowed is not None:
                    return {k: v for k, v in render.items() if k in allowed}
                return {k: v for k, v in _flatten(render).items()
                        if not set(k.split(".")) & _NOT_AXES}
    try:
        from render.variants import get_variant

        return get_variant(variant).settings()
    except (ImportError, ValueError):  # a user's variant the registry does not know: no axes
        return {}


def texture_family(settings: dict, variant: str) -> str:
    """The texture family (random / grid / color / ...) of a variant, for Table 3's rows."""
    for key, value in settings.items():
        if key.rsplit(".", 1)[-1] == "texture" and isinstance(value, str):
            return value
    return variant


class _Rngs:
    """Bootstrap generators derived from the run seed and the cell: reruns give the same intervals."""

    def __init__(self, seed: int):
        self.seed = seed

    def __call__(self, *key: str) -> np.random.Generator:
        return seeding.rng(self.seed, 0, seeding.EVAL, "bootstrap", *[str(k) for k in key])


def prediction_path(run: Run, m: TrainedModel, test_variant: str) -> Path:
    return run.eval_dir / "predictions" / m.setting / m.variant / m.model / f"s{m.seed}" / f"{test_variant}.csv"


def _rel(run: Run, path: Path) -> str:
    try:
        return str(path.relative_to(run.root))
    except ValueError:
        return str(path)


def record_path(prediction: Path) -> Path:
    """The record beside a prediction CSV: what it was computed on (written after the CSV)."""
    return prediction.with_suffix(".json")


def read_record(path: Path) -> dict | None:
    """The record beside prediction file ``path`` (which checkpoint made it), or None when missing or unreadable."""
    try:
        record = json.loads(record_path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return record if isinstance(record, dict) else None


def _left_out_reason(clip_dir: Path, caught: list[warnings.WarningMessage]) -> str:
    for w in caught:
        text = str(w.message)
        if str(clip_dir) in text or f"clip {clip_dir.name}" in text or f"{clip_dir.name}:" in text:
            return text.removesuffix(LEFT_OUT)
    return "no sub-sequence predicted (fewer frames than one sub-sequence, or unreadable)"


def predict_all(run: Run, models: list[TrainedModel], predictor: Predictor,
                progress: bool) -> tuple[dict[tuple, tables.Cell], dict[str, int], list[dict]]:
    """Predictions of every model on every rendered test variant, gathered into cells.

    A prediction CSV is reused only when its record says it was computed from the same
    checkpoint bytes (sha256) on the same test clips with none left out; otherwise it is
    deleted first and computed again, so a changed or corrupt checkpoint can never stand
    behind old numbers. Also returns every test clip that has no prediction (not rendered,
    or unreadable), one row per (model, test variant, clip).

    Models are predicted setting by setting and, within a setting, test variant by test variant,
    so that a caching predictor reads each test variant's frames once for all of them; the cells
    and the clips left out are gathered in ``models``' order.
    """
    by_setting: dict[str, list[int]] = {}
    for i, m in enumerate(models):
        by_setting.setdefault(m.setting, []).append(i)
    counts = {"predicted": 0, "reused": 0, "no_test_clips": 0}
    variants_of: dict[str, list[str]] = {}
    done: dict[tuple[int, str], tuple[pd.DataFrame | None, list[dict]]] = {}   # (model, test variant) -> ...
    for setting, members in by_setting.items():
        windows = test_windows(run, setting)
        test_ids = sorted(windows)
        shas = {i: checkpoint_sha256(models[i]) for i in members}
        variants_of[setting] = rendered_variants(run, setting)
        for test_variant in variants_of[setting]:
            folder = run.render_dir(test_variant, setting)
            missing = [{"clip_id": c, "reason": f"not rendered ({folder / c} has no DONE)"}
                       for c in test_ids if not is_done(folder / c)]
            for i in members:
                m = models[i]
                frame, dropped = _model_predictions(run, m, test_variant, test_ids, shas[i], predictor, progress,
                                                    counts)
                if frame is None:
                    done[i, test_variant] = None, missing
                    continue
                for item in missing + dropped:
                    if progress:
                        print(f"[eval] left out {test_variant}/{m.setting}/{item['clip_id']} for "
                              f"{_rel(run, m.folder)}: {item['reason']}", file=sys.stderr, flush=True)
                done[i, test_variant] = only_windows(frame, windows).assign(seed=m.seed), missing + dropped

    cells: dict[tuple, tables.Cell] = {}
    left_out: list[dict] = []
    for i, m in enumerate(models):
        for test_variant in variants_of[m.setting]:
            frame, items = done[i, test_variant]
            where = {"setting": m.setting, "train_variant": m.variant, "model": m.model, "seed": m.seed,
                     "test_variant": test_variant}
            left_out += [{**where, **x} for x in items]
            if frame is None:
                continue
            key = (m.setting, m.variant, m.model, test_variant)
            if key in cells:
                cells[key].frame = pd.concat([cells[key].frame, frame], ignore_index=True)
                cells[key].sources.append(_rel(run, m.checkpoint))
            else:
                cells[key] = tables.Cell(*key, frame=frame, sources=[_rel(run, m.checkpoint)])
    return cells, counts, left_out


def _model_predictions(run: Run, m: TrainedModel, test_variant: str, test_ids: list[str], sha: str,
                       predictor: Predictor, progress: bool,
                       counts: dict[str, int]) -> tuple[pd.DataFrame | None, list[dict]]:
    """Model ``m``'s predictions on the rendered test clips of ``test_variant``, reused when their record matches
    (``predict_all``), else computed and saved; and the clips left out of them, with the reason. The frame is
    None when no test clip is rendered. ``counts`` counts what was reused, predicted, or had no test clip."""
    path = prediction_path(run, m, test_variant)
    folder = run.render_dir(test_variant, m.setting)
    clip_dirs = [folder / c for c in test_ids if is_done(folder / c)]
    wanted = [d.name for d in clip_dirs]
    record = read_record(path)
    if (path.is_file() and record is not None and record.get("checkpoint_sha256") == sha
            and record.get("clips") == wanted and not record.get("left_out")):
        counts["reused"] += 1
        return preds.load(path), []
    # Stale or unverifiable: gone before predicting, so a failure cannot leave it to be reused.
    path.unlink(missing_ok=True)
    record_path(path).unlink(missing_ok=True)
    if not clip_dirs:
        counts["no_test_clips"] += 1
        return None, []
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        raw = predictor(m.folder, clip_dirs)
    got = set(preds.to_flat(raw)["clip_id"])
    dropped = [{"clip_id": d.name, "reason": _left_out_reason(d, caught)} for d in clip_dirs if d.name not in got]
    preds.save(raw, path)
    atomic_write_json(record_path(path), {"checkpoint": _rel(run, m.checkpoint), "checkpoint_sha256": sha,
                                          "clips": wanted, "left_out": dropped})
    frame = preds.load(path)
    counts["predicted"] += 1
    if progress:
        n = len(wanted) - len(dropped)
        print(f"[eval] {_rel(run, m.folder)} on {test_variant}: {n} of {len(test_ids)} test clips, "
              f"{len(frame)} sub-sequences, {time.perf_counter() - t0:.1f} s", flush=True)
    return frame, dropped


# A confusion figure takes 0.2-0.4 s of matplotlib: a study's 90-odd of them are drawn in a process pool (while
# the tables are computed) when the host has the CPUs; a few stay in this process (spawning costs seconds).
CONFUSION_POOL_MIN_FIGURES = 16
CONFUSION_POOL_MIN_CPUS = 2
CONFUSION_POOL_MAX = 8          # each worker imports matplotlib and pandas (~1 s): more would not pay on 90 figures


def _draw_confusion(counts: np.ndarray, title: str, true_classes: list[int], path: Path) -> None:
    figures.save(figures.confusion(counts, title, true_classes), path)


@contextlib.contextmanager
def _confusion_figures(run: Run, cells: dict[tuple, tables.Cell]) -> Iterator[list[str]]:
    """One confusion-matrix PNG per cell, drawn in a pool of spawned processes (while the block runs) or here
    (when it ends), as ``pool_size`` says. Yields their paths relative to the run; leaving the block waits for every
    figure and raises a worker's error."""
    true_classes = list(run.config.sim.class_indices())
    jobs, written = [], []
    for (setting, train_v, model, test_v), cell in sorted(cells.items()):
        counts = metrics.confusion_matrix(cell.frame["class_index"], cell.frame["pred"])
        acc = metrics.accuracy(cell.frame["class_index"], cell.frame["pred"])
        title = f"{setting}: {model} trained on {train_v}, tested on {test_v} (acc {100 * acc:.1f}%)"
        path = run.eval_dir / "figures" / "confusion" / setting / train_v / model / f"{test_v}.png"
        jobs.append((counts, title, true_classes, path))
        written.append(_rel(run, path))
    processes = min(CONFUSION_POOL_MAX, pool_size(len(jobs), CONFUSION_POOL_MIN_FIGURES, CONFUSION_POOL_MIN_CPUS))
    if processes <= 1:
        yield written
        for job in jobs:
            _draw_confusion(*job)
        return
    pool = spawn_pool(processes)
    try:
        drawn = pool.map(_draw_confusion, *zip(*jobs), chunksize=chunk_size(len(jobs), processes))
        yield written
        list(drawn)
    finally:
        pool.shutdown(cancel_futures=True)


def _gap_figures(run: Run, gap: pd.DataFrame) -> list[str]:
    written = []
    for (setting, model), _ in gap.groupby(["setting", "model"]):
        matrix = tables.gap_matrix(gap, setting, model)
        if matrix.shape[1] < 2 and matrix.shape[0] < 2:
            continue
        path = run.eval_dir / "figures" / "gap" / setting / f"{model}.png"
        figures.save(figures.gap_heatmap(matrix, f"{setting}, {model}: accuracy by train/test variant"), path)
        written.append(_rel(run, path))
    return written


def run_eval(run: Run, progress: bool = True, predictor: Predictor | None = None) -> dict:
    """Evaluate every finished model of the run on every rendered test variant; write the tables.

    Args:
        run: the run whose finished models and rendered test clips are evaluated.
        progress: print a line per prediction file and per clip left out.
        predictor: replaces ``learn.predict.predict_clips`` (tests inject a stub).

    Returns:
        A short summary (the full one is ``eval/summary.json``).
    """
    cfg = run.config
    models = finished_models(run)
    if not models:
        raise ConfigError(f"no finished train folder under {run.train_root} for the config's "
                          f"settings/variants/models/seeds: run `clothgap train {run.root}` first")
    # Seconds per part, printed with the short summary (not in summary.json, which a rerun rewrites byte for
    # byte): where a study's eval time goes.
    seconds: dict[str, float] = {}
    with timed(seconds, "predict"):
        cells, counts, left_out = predict_all(run, models, predictor or _default_predictor(), progress)
        if cfg.eval.seed_ensemble:
            cells.update({c.key: c for c in tables.ensemble_cells(list(cells.values()))})
    if not cells:
        raise _no_test_clips_error(run, models)
    with timed(seconds, "tables_and_figures"):
        with _confusion_figures(run, cells) as confusion:
            written = _write_tables(run, cells)
        figs = {"confusion": confusion, "gap": _gap_figures(run, written.gap)}
    in_domain = written.results[written.results["in_domain"]]
    headline = {f"{r.setting}/{r.train_variant}/{r.model}": round(float(r.acc), 4) for r in in_domain.itertuples()}
    summary = _summary(run, models, written, figs, headline, counts, left_out)
    out = run.eval_dir
    atomic_write_json(out / "summary.json", summary)
    short = {"cells": len(cells), **counts, "left_out": len(left_out), "in_domain_accuracy": headline}
    if left_out:
        short["left_out_clips"] = sorted({f"{x['test_variant']}/{x['setting']}/{x['clip_id']}" for x in left_out})

    # Optional parts, each resumable: the sim stage's material analyses and the measured-fabric set.
    if cfg.eval.sim_analysis:
        with timed(seconds, "sim_analysis"):
            summary["sim_analysis"] = short["sim_analysis"] = run_sim_analysis(run, progress)
        atomic_write_json(out / "summary.json", summary)
    if cfg.eval.measured_sequences > 0:
        from eval.measured import run_measured

        with timed(seconds, "measured"):
            short["measured"] = run_measured(run, models=models, predictor=predictor, progress=progress)
        summary["files"]["measured"] = {"fabrics": "eval/measured.csv",
                                        "correlations": "eval/measured_correlations.csv",
                                        "markdown": "eval/measured.md", "summary": "eval/measured.json"}
        atomic_write_json(out / "summary.json", summary)
    short["seconds"] = {part: round(s, 1) for part, s in seconds.items()}
    return short


def _no_test_clips_error(run: Run, models: list[TrainedModel]) -> ConfigError:
    """Why no model has a test clip to predict, and what would give it one."""
    cfg = run.config
    empty = [s for s in sorted({m.setting for m in models}) if not test_clips(run, s)]
    if empty:
        # A split can hold no test sequence at all (too few sequences per class for the test share);
        # rendering more would not help, so say what would.
        return ConfigError(f"the split of {', '.join(empty)} holds no test sequence "
                           f"({cfg.sim.sequences_per_class} sequence(s) per class, train.test_fraction="
                           f"{cfg.train.test_fraction:g}): raise sim.sequences_per_class or train.test_fraction "
                           "in a new run")
    return ConfigError(f"no rendered test clips found for any model under {run.render_root}: "
                       f"run `clothgap render {run.root}` first")


@dataclass
class _Tables:
    """What ``_write_tables`` computed and wrote, for the figures and the summary."""

    results: pd.DataFrame
    gap: pd.DataFrame
    ranking: pd.DataFrame
    variants: list[str]
    settings_of: dict[str, dict]     # variant -> its render settings
    texture_of: dict[str, str]       # variant -> its texture family


def _write_tables(run: Run, cells: dict[tuple, tables.Cell]) -> _Tables:
    """results.csv, table3.csv and .md, domain_gap.csv and axis_ranking.csv from the gathered cells."""
    cfg, out = run.config, run.eval_dir
    rng_for = _Rngs(cfg.seed)
    opts = {"resamples": cfg.eval.bootstrap, "confidence": cfg.eval.confidence, "rng_for": rng_for}
    ordered = [cells[k] for k in sorted(cells)]
    results = tables.results_frame(ordered, **opts)
    atomic_write_text(out / "results.csv", results.to_csv(index=False, float_format="%.6g"))

    variants = sorted({k[1] for k in cells} | {k[3] for k in cells})
    settings_of = {v: variant_settings(run, v) for v in variants}
    texture_of = {v: texture_family(settings_of[v], v) for v in variants}
    table3 = tables.table3(results, texture_of)
    atomic_write_text(out / "table3.csv", table3.to_csv(index=False, float_format="%.6g"))
    atomic_write_text(out / "table3.md", f"# Table 3 ({cfg.name}: `{run.root}`)\n\n" + tables.table3_markdown(table3))

    gap = tables.domain_gap(cells, results, **opts, reference=cfg.render.variants[0])
    atomic_write_text(out / "domain_gap.csv", gap.to_csv(index=False, float_format="%.6g"))
    ranking = tables.rank_axes(gap, settings_of, cells, resamples=cfg.eval.bootstrap, confidence=cfg.eval.confidence,
                               rng=rng_for("axes"))
    atomic_write_text(out / "axis_ranking.csv", ranking.to_csv(index=False, float_format="%.6g"))
    return _Tables(results, gap, ranking, variants, settings_of, texture_of)


def _summary(run: Run, models: list[TrainedModel], written: _Tables, figs: dict, headline: dict,
             counts: dict[str, int], left_out: list[dict]) -> dict:
    """``eval/summary.json``: the models and their checkpoints, the tables' rows, the files, what was left out."""
    cfg = run.config
    return {
        "run": str(run.root), "config": "config.json", "name": cfg.name,
        "bootstrap": {"resamples": cfg.eval.bootstrap, "confidence": cfg.eval.confidence, "unit": "sequence"},
        "models": [{"setting": m.setting, "variant": m.variant, "model": m.model, "seed": m.seed,
                    "checkpoint": _rel(run, m.checkpoint), "checkpoint_sha256": checkpoint_sha256(m)}
                   for m in models],
        "test_variants": written.variants, "texture_of": written.texture_of,
        "variant_axes": tables.differing_axes(written.settings_of),
        "axis_groups": tables.axis_groups(written.settings_of),
        "in_domain_accuracy": headline,
        "results": json.loads(written.results.to_json(orient="records")),
        "axis_ranking": json.loads(written.ranking.to_json(orient="records")),
        "files": {"results": "eval/results.csv", "table3": "eval/table3.csv", "table3_md": "eval/table3.md",
                  "domain_gap": "eval/domain_gap.csv", "axis_ranking": "eval/axis_ranking.csv",
                  "figures": figs},
        "predictions": counts,
        # Test clips of the split with no prediction (not rendered, unreadable): the numbers above are on
        # fewer clips than the split names, and the CLI exits non-zero unless --allow-failures.
        "left_out": left_out,
        "config_snapshot": to_dict(cfg),
    }


def stale_checkpoints(run: Run) -> list[str]:
    """Checkpoints named in ``eval/summary.json`` whose bytes changed (or vanished) since that eval."""
    path = run.eval_dir / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return []
    stale = []
    for m in summary.get("models", []) if isinstance(summary, dict) else []:
        sha = m.get("checkpoint_sha256")
        if not sha:
            continue            # an eval from before checkpoints were hashed: nothing to compare
        ckpt = run.root / m["checkpoint"]
        if not ckpt.is_file() or file_sha256(ckpt) != sha:
            stale.append(m["checkpoint"])
    return stale


SIM_ANALYSES = ("table2", "sensitivity")


def run_sim_analysis(run: Run, progress: bool = True) -> dict[str, str]:
    """The sim stage's analyses named in ``eval.sim_analysis`` into ``RUN/sim_analysis`` (kept when present).

    ``table2``: the paper's Table 2 (``sim.analysis.table2``: the basis sweep and every fabric simulated);
    ``sensitivity``: its Fig. 3 curves (``sim.analysis.sensitivity``). Both simulate on ``sim.device``.
    The same files as ``clothgap sim table2|sensitivity --out RUN/sim_analysis``.
    """
    unknown = [a for a in run.config.eval.sim_analysis if a not in SIM_ANALYSES]
    if unknown:
        raise ConfigError(f"eval.sim_analysis: unknown analysis {', '.join(unknown)}; known: {', '.join(SIM_ANALYSES)}")
    out = run.sim_analysis_dir
    done: dict[str, str] = {}
    for name in run.config.eval.sim_analysis:
        last = out / ("table2.csv" if name == "table2" else "sensitivity.png")   # written last
        if not last.is_file():
            t0 = time.perf_counter()
            from sim import analysis
            from sim.solver import resolve_device

            device = resolve_device(run.config.sim.device)
            if name == "table2":
                analysis.table2(out, device=device)
            else:
                analysis.sensitivity(out, device=device)
            if progress:
                print(f"[eval] sim analysis {name}: {time.perf_counter() - t0:.1f} s", flush=True)
        done[name] = _rel(run, last)
    return done
