"""The measured-fabric test set: the platform's stand-in for real video.

``run_measured(run)`` (``clothgap eval measured RUN_DIR``, and part of
``clothgap eval`` when ``eval.measured_sequences`` > 0):

1. **simulate** the Wang et al. 2011 fabrics with their own full tables
   (``sim.measured``: not the scaled basis), ``eval.measured_sequences`` clips
   per fabric under every setting of the run (its motions, each clip with its
   own wind / arm draws), into ``RUN/measured/sim/<setting>/<fabric>-<n>/``;
2. **render** them with the render stage's code under ``eval.measured_variant``
   (default ``heldout``: no training variant uses it) into
   ``RUN/measured/render/<variant>/<setting>/<fabric>-<n>/``; the meta names the
   ``fabric``;
3. **predict** them through the real-video path: every finished model of the run
   gets ``eval.real.evaluate_real`` on the clips' ``ldr/`` frame folders, read where
   they lie (frames -> ``train.clip_len``-frame sub-sequences -> mean probabilities per clip; Table 4 against the
   measured bending stiffness and density), in
   ``eval/measured/<variant>/<setting>/<train_variant>/<model>/s<seed>/``
   (``videos.csv``, ``table4.csv/.md``, ``truth.csv``, ``scatter.png``,
   ``activations.png``, ``DONE``);
4. **compare** per fabric: its class is the argmax of its clips' mean
   probabilities, set beside the class the paper's Table 2 gives it (exact,
   p and k match, grid steps), and **correlate** (``eval.metrics``, Pearson and
   Spearman with percentile bootstrap intervals) the predictions with the
   fabric's measured stiffness and density (definitions in ``sim.measured``):
   per clip, resampling whole fabrics, and per fabric;
5. **ensemble** the models that differ only in their seed (same setting,
   training variant, network and recipe): per clip the mean of their
   probabilities, scored like one more model, apart from the models' tables
   (``ensemble-s0+1/`` beside its members' folders).

Every step skips finished work (DONE markers on clips and on each model's
folder); the tables are rebuilt from those folders each time. Outputs:

``eval/measured.csv``               one row per (model, fabric): prediction, Table 2 class, matches,
                                    measured and predicted stiffness, checkpoint
``eval/measured_correlations.csv``  one row per (model, unit, score, target): Pearson / Spearman + intervals
``eval/measured_ensembles.csv``     one row per (seeds' ensemble, fabric), as measured.csv, its ``seed`` the
                                    members' seeds as text (``0+1``); only when two seeds of a model were scored
``eval/measured.md``, ``eval/measured.json``  the same for people and programs (match rates with intervals,
                                    definitions, generation summaries, files; each model's and ensemble's
                                    measured.csv rows as numbers under its "per_fabric"; the ensembles under
                                    "ensembles")

Pearson is taken on the raw values, as in Table 4 (``eval.real``); Spearman on ranks.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from clothgap import seeding
from clothgap.errors import ConfigError
from clothgap.parallel import host_processes, pool_map
from clothgap.runs import Run, atomic_write_json, atomic_write_text, fresh_dir, is_done, mark_done, select_clips
from eval import classes, metrics, real
from eval import predictions as preds
from eval.trained import TrainedModel, checkpoint_sha256, finished_models
from sim.phases import timed

DEFAULT_SEQUENCES = 2       # `clothgap eval measured` when the run's eval.measured_sequences is 0
# Scoring a model is mostly host work besides the network: reading the clips at its image size, its figures and
# bootstraps. A study scores dozens of models
# (48 in the `study` preset), so on a host of POOL_MIN_CPUS or more they are scored in a spawned pool, a process
# for every CPUS_PER_SCORER CPUs, when there are POOL_MIN_MODELS or more.
POOL_MIN_MODELS = 4
POOL_MIN_CPUS = 8
CPUS_PER_SCORER = 4
MATCH_SCORES = ("exact", "p_match", "k_match", "within1", "class_dist", "within1_tables", "k_within1_tables")
LABELS = {
    "pred_bending_N_m": "predicted bending (k x basis, N*m)",
    "pred_stretching_N_m": "predicted stretching (p x basis, N/m)",
    "class_index": "class index (paper)",
    "pred_p": "predicted p", "pred_k": "predicted k",
    "bending_N_m": "measured bending (N*m)", "stretching_N_m": "measured stretching (N/m)",
    "density_kg_m2": "density (kg/m^2)", "table2_p_est": "Table 2 p~", "table2_k_est": "Table 2 k~",
}
# (unit, score, target): per clip the bootstrap resamples whole fabrics; per fabric, fabrics.
CORRELATIONS = (
    ("clip", "pred_bending_N_m", "bending_N_m"), ("clip", "pred_stretching_N_m", "stretching_N_m"),
    ("clip", "class_index", "bending_N_m"), ("clip", "pred_bending_N_m", "density_kg_m2"),
    ("clip", "class_index", "density_kg_m2"),
    ("fabric", "pred_bending_N_m", "bending_N_m"), ("fabric", "pred_stretching_N_m", "stretching_N_m"),
    ("fabric", "pred_p", "table2_p_est"), ("fabric", "pred_k", "table2_k_est"),
    ("fabric", "density_kg_m2", "bending_N_m"),          # no prediction: the rank weight alone gives the bending
)
MODEL_KEYS = ["setting", "train_variant", "model", "seed", "test_variant"]

Predictor = Callable[[Path, list[Path]], pd.DataFrame]


# ------------------------------------------------------------------ what to make

def resolve(run: Run, sequences: int | None = None, fabrics: Sequence[str] | None = None,
            variant: str | None = None) -> tuple[int, list[str], str]:
    """(sequences, fabrics, variant): the arguments, else the run's eval config, else the defaults."""
    from render.variants import VariantError, get_variant
    from sim.measured import MAX_SEQUENCES, check_fabrics, table2_fabrics

    cfg = run.config.eval
    sequences = sequences if sequences is not None else (cfg.measured_sequences or DEFAULT_SEQUENCES)
    if not 0 < sequences <= MAX_SEQUENCES:
        raise ConfigError(f"measured sequences per fabric must be 1..{MAX_SEQUENCES}, got {sequences}")
    fabrics = check_fabrics(list(fabrics or cfg.measured_fabrics or table2_fabrics()))
    variant = variant or cfg.measured_variant
    try:
        get_variant(variant)
    except VariantError as err:
        raise ConfigError(f"eval.measured_variant: {err}") from None
    return sequences, fabrics, variant


def model_folder(run: Run, m, variant: str) -> Path:
    """Where model ``m``'s predictions of the measured clips in ``variant`` go (a recipe's models apart)."""
    root = run.eval_dir / "measured" / variant
    if m.recipe:
        root = root / "ablation" / m.recipe
    return root / m.setting / m.variant / m.model / f"s{m.seed}"


def model_from_dir(run: Run, train_dir: Path) -> TrainedModel:
    """The TrainedModel of a finished train folder of the run: ``RUN/train/<setting>/<variant>/<model>/s<seed>``,
    or a training recipe's ``RUN/ablation/<recipe>/<setting>/<variant>/<model>/s<seed>``."""
    expected = (f"expected {run.train_root}/<setting>/<variant>/<model>/s<seed> or "
                f"{run.root / 'ablation'}/<recipe>/<setting>/<variant>/<model>/s<seed>")
    try:
        parts = Path(train_dir).resolve().relative_to(run.root.resolve()).parts
    except ValueError:
        raise ConfigError(f"--model {train_dir} is not a train folder of the run {run.root} ({expected})") from None
    recipe = ""
    if parts[:1] == ("ablation",) and len(parts) == 6:
        recipe, parts = parts[1], parts[2:]
    elif parts[:1] == ("train",) and len(parts) == 5:
        parts = parts[1:]
    else:
        raise ConfigError(f"--model {train_dir}: {expected}")
    if not parts[3].startswith("s") or not parts[3][1:].isdigit():
        raise ConfigError(f"--model {train_dir}: {expected}")
    if not is_done(Path(train_dir)):
        raise ConfigError(f"--model {train_dir} has no DONE marker: is that training finished?")
    root = run.ablation_dir(recipe) if recipe else run.train_root
    return TrainedModel(*parts[:3], int(parts[3][1:]), root.joinpath(*parts), recipe)


def make_clips(run: Run, sequences: int, fabrics: Sequence[str], variant: str, progress: bool = True,
               units: Sequence[tuple[str, str, int]] | None = None) -> dict:
    """Simulate and render the measured clips that are not finished yet, or only ``units`` ((setting, fabric,
    sequence), a shard of ``generation_units``); returns both summaries."""
    from render.stage import render_measured
    from sim.measured import clip_name
    from sim.stage import simulate_measured

    if units is None:
        units = _units(run, sequences, fabrics)
    by_setting: dict[str, list[tuple[str, int]]] = {}
    for setting, fabric, n in units:
        by_setting.setdefault(setting, []).append((fabric, n))
    sim_summary = simulate_measured(run, fabrics, sequences, progress, clips=by_setting)
    render_summary = render_measured(run, variant, {s: [clip_name(f, n) for f, n in c] for s, c in by_setting.items()},
                                     progress)
    return {"sim": sim_summary, "render": render_summary}


def generation_units(run: Run) -> list[tuple[str, str, int]]:
    """(setting, fabric, sequence) of every measured clip the run's config asks for, setting by setting: what a
    sharded generation (``clothgap eval --executor``) splits, so that a shard holds few settings and a GPU batch
    of each."""
    sequences, fabrics, _ = resolve(run)
    return _units(run, sequences, fabrics)


def _units(run: Run, sequences: int, fabrics: Sequence[str]) -> list[tuple[str, str, int]]:
    from sim.measured import wanted_clips

    return [(s, f, n) for s in run.config.sim.settings() for f, n in wanted_clips(fabrics, sequences)]


def make_measured_clips(run: Run, progress: bool = True, indices: Sequence[int] | None = None) -> dict:
    """``make_clips`` of the run's config (``eval.measured_*``), or of ``indices`` into ``generation_units`` (a
    shard's, for ``merge_shard_summaries``)."""
    sequences, fabrics, variant = resolve(run)
    units = _units(run, sequences, fabrics)
    return make_clips(run, sequences, fabrics, variant, progress, [units[i] for i in select_clips(len(units), indices)])


def merge_shard_summaries(parts: list[dict]) -> dict:
    """One ``make_measured_clips`` summary from its shards': the sim and render stages' own merges."""
    from render.stage import merge_shard_summaries as merge_render
    from sim.stage import merge_shard_summaries as merge_sim

    return {"sim": merge_sim([p["sim"] for p in parts]), "render": merge_render([p["render"] for p in parts])}


# ------------------------------------------------------------------ prediction (the real-video path)

def _clip_fabrics(folder: Path, names: Sequence[str]) -> dict[str, str]:
    """Finished rendered clips among ``names`` and the fabric their meta names."""
    out = {}
    for name in names:
        clip = folder / name
        if is_done(clip):
            fabric = json.loads((clip / "meta.json").read_text()).get("fabric")
            if not isinstance(fabric, str):
                raise ValueError(f"{clip / 'meta.json'} names no fabric (a measured clip's meta has 'fabric')")
            out[name] = fabric
    return out


def predict_model(run: Run, m, variant: str, names: Sequence[str], *, predictor: Predictor | None = None,
                  activations: int = 2, progress: bool = True) -> tuple[pd.DataFrame | None, str]:
    """Per-clip predictions of model ``m`` on the measured clips, through ``eval.real.evaluate_real``.

    Returns (videos frame with ``fabric`` and truth columns, or None when no clip is rendered; status).
    Kept when the model's folder is finished for the same clips.
    """
    from sim.measured import measured_values

    clips = _clip_fabrics(run.measured_render_dir(variant, m.setting), names)
    if not clips:
        return None, "no rendered measured clips"
    folder = model_folder(run, m, variant)
    status = "reused"
    done = folder / "DONE"
    sha = checkpoint_sha256(m)
    record = json.loads(done.read_text()) if done.is_file() else {}
    # Kept only for the same clips and the same weights: a model retrained in place is predicted again.
    if not (record.get("clips") == sorted(clips) and record.get("checkpoint_sha256") == sha):
        status = "predicted"
        fresh_dir(folder)
        truth = pd.DataFrame([{"video": n, "label": f, "bending_N_m2": measured_values(f)["bending_N_m"],
                               "area_weight_kg_m2": measured_values(f)["density_kg_m2"]} for n, f in clips.items()])
        atomic_write_text(folder / "truth.csv", truth.to_csv(index=False, float_format="%.8g"))
        render_dir = run.measured_render_dir(variant, m.setting)
        t0 = time.perf_counter()
        try:
            real.evaluate_real(render_dir, folder / "truth.csv", m.folder, folder,
                               max_frames=run.config.sim.frames, resamples=run.config.eval.bootstrap,
                               confidence=run.config.eval.confidence, seed=run.config.seed,
                               activations=activations, predictor=predictor, progress=False,
                               inputs={n: render_dir / n / "ldr" for n in sorted(clips)})
        except real.VideoError as err:     # e.g. clips shorter than the model's sub-sequence
            raise ConfigError(f"measured clips of {m.setting} cannot be predicted by {m.folder}: {err}") from None
        mark_done(folder, {"clips": sorted(clips), "checkpoint": str(m.checkpoint), "checkpoint_sha256": sha})
        if progress:
            print(f"[eval measured] {m.setting}/{m.variant}/{m.model}/s{m.seed} on {variant}: {len(clips)} clips, "
                  f"{time.perf_counter() - t0:.1f} s", flush=True)
    return with_fabrics(pd.read_csv(folder / "videos.csv", dtype={"video": str}), clips), status


def with_fabrics(videos: pd.DataFrame, clips: dict[str, str]) -> pd.DataFrame:
    """Per-clip predictions with each clip's fabric (``clips``: clip name -> fabric) and its measured values."""
    from sim.measured import measured_values

    videos = videos.assign(fabric=videos["video"].map(clips))
    for key in ("stretching_N_m", "bending_N_m", "density_kg_m2"):
        videos[key] = videos["fabric"].map(lambda f, k=key: measured_values(f)[k])
    return videos


# ------------------------------------------------------------------ tables

def fabric_table(videos: pd.DataFrame) -> pd.DataFrame:
    """One row per fabric: the argmax of its clips' mean probabilities beside the paper's Table 2 class."""
    from sim.analysis import PAPER_TABLE2
    from sim.measured import basis_values, measured_values, table2_class, tables_class

    basis = basis_values()
    rows = []
    for fabric, g in videos.groupby("fabric", sort=False):
        probs = g[preds.PROB_COLUMNS].to_numpy(float).mean(axis=0)
        pred = int(probs.argmax())
        truth = table2_class(fabric)
        p_est, p_t2, k_est, k_t2 = PAPER_TABLE2.get(fabric, (np.nan,) * 4)
        values = measured_values(fabric)
        pred_p, pred_k = float(classes.p_value(pred)), float(classes.k_value(pred))
        tables = tables_class(fabric)      # a diagnostic beside Table 2's class (the goal's label)
        rows.append({
            "fabric": fabric, "clips": len(g), "pred": pred, "pred_p": pred_p, "pred_k": pred_k,
            "prob": float(probs[pred]), "vote_share": float((g["pred"] == pred).mean()),
            "table2_p_est": p_est, "table2_k_est": k_est, "table2_p": float(classes.p_value(truth)),
            "table2_k": float(classes.k_value(truth)), "table2_class": truth,
            "class_source": "paper Table 2" if fabric in PAPER_TABLE2 else "nearest class to estimated ratios",
            "exact": float(pred == truth), "p_match": float(metrics.stretch_correct([truth], [pred])[0]),
            "k_match": float(metrics.bend_correct([truth], [pred])[0]),
            "within1": float(metrics.within_one_bin([truth], [pred])[0]),
            "class_dist": float(metrics.class_distance([truth], [pred])[0]),
            "tables_class": tables, "tables_p": float(classes.p_value(tables)),
            "tables_k": float(classes.k_value(tables)),
            "within1_tables": float(metrics.within_one_bin([tables], [pred])[0]),
            "k_within1_tables": float(metrics.bend_within_one([tables], [pred])[0]),
            **values, "pred_stretching_N_m": pred_p * basis["stretching_N_m"],
            "pred_bending_N_m": pred_k * basis["bending_N_m"]})
    return pd.DataFrame(rows)


def with_predicted_values(videos: pd.DataFrame) -> pd.DataFrame:
    """Per-clip predicted p, k and the stiffness they stand for (the basis's value times p or k)."""
    from sim.measured import basis_values

    basis = basis_values()
    out = videos.copy()
    out["pred_p"] = classes.p_value(out["pred"].to_numpy())
    out["pred_k"] = classes.k_value(out["pred"].to_numpy())
    out["pred_stretching_N_m"] = out["pred_p"] * basis["stretching_N_m"]
    out["pred_bending_N_m"] = out["pred_k"] * basis["bending_N_m"]
    out["class_index"] = out["pred"]
    return out


def correlation_table(videos: pd.DataFrame, fabrics: pd.DataFrame, *, resamples: int, confidence: float,
                      rng_for: Callable[..., np.random.Generator]) -> pd.DataFrame:
    """Pearson and Spearman (with intervals) of each ``CORRELATIONS`` pair."""
    clips = with_predicted_values(videos)
    rows = []
    for unit, score, target in CORRELATIONS:
        frame = clips if unit == "clip" else fabrics.dropna(subset=[target])
        row = {"unit": unit, "score": score, "target": target, "description": f"{LABELS[score]} vs {LABELS[target]}",
               "n": len(frame), "fabrics": int(frame["fabric"].nunique())}
        for method in ("pearson", "spearman"):
            est = metrics.bootstrap_correlation(frame[score], frame[target], method=method,
                                                groups=frame["fabric"] if unit == "clip" else None,
                                                resamples=resamples, confidence=confidence,
                                                rng=rng_for(unit, score, target, method))
            row.update(est.as_dict(method))
        rows.append(row)
    return pd.DataFrame(rows)


def match_table(fabrics: pd.DataFrame, *, resamples: int, confidence: float,
                rng_for: Callable[..., np.random.Generator]) -> pd.DataFrame:
    """Mean of each match score over fabrics, with an interval from resampling fabrics."""
    rows = [{"score": s, "fabrics": len(fabrics),
             **metrics.bootstrap_mean(fabrics[s], fabrics["fabric"], resamples=resamples, confidence=confidence,
                                      rng=rng_for("match", s)).as_dict("value")} for s in MATCH_SCORES]
    return pd.DataFrame(rows, columns=["score", "fabrics", "value", "value_lo", "value_hi"])


def _fmt(value, lo, hi, digits: int = 2) -> str:
    return metrics.Estimate(value, lo, hi).fmt(1.0, digits)


def markdown(run: Run, variant: str, heldout: bool, table: pd.DataFrame, corr: pd.DataFrame,
             match: pd.DataFrame, ensembles: tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame] | None = None) -> str:
    """``measured.md``: a section per model (fabrics, match rates, correlations), then one per seeds' ensemble."""
    lines = [f"# Measured fabrics (`{run.root}`, render variant `{variant}`"
             f"{'' if heldout else ', NOT held out: a model was trained on it'})", "",
             "Each fabric simulated with its own Wang et al. 2011 tables, predicted through the real-video path "
             "(mean sub-sequence probabilities per clip, then per fabric), beside the class of the paper's Table 2.",
             ""]
    lines += _sections(table, corr, match, ensemble=False)
    if ensembles is not None:
        lines += _sections(*ensembles, ensemble=True)
    return "\n".join(lines)


def reading_title(model: str, train_variant: str, setting: str, seed, ensemble: bool = False) -> str:
    """The title of a model's (or a seeds' ensemble's, ``seed`` then "0+1") section in ``measured.md``: the name a
    reading of the measured fabrics goes by (scripts/gather_lease.py keys its tables by it)."""
    who = f"seeds {seed}, their ensemble: mean probabilities per clip" if ensemble else f"seed {seed}"
    return f"{model} trained on {train_variant} ({setting}, {who})"


def _sections(table: pd.DataFrame, corr: pd.DataFrame, match: pd.DataFrame, ensemble: bool) -> list[str]:
    """The markdown sections of the models (or ensembles) in ``table``, in its order."""
    lines = []
    for key, g in table.groupby(MODEL_KEYS, sort=True):
        setting, train_v, model, seed, test_v = key
        kmask = np.logical_and.reduce([corr[c] == v for c, v in zip(MODEL_KEYS, key)])
        mmask = np.logical_and.reduce([match[c] == v for c, v in zip(MODEL_KEYS, key)])
        lines += [f"## {reading_title(model, train_v, setting, seed, ensemble)}", "",
                  f"Checkpoint: `{'`, `'.join(str(g['checkpoint'].iloc[0]).split())}`", "",
                  "| Fabric | Clips | Predicted (p, k) | Table 2 (p, k) | Exact | p | k | Within one bin | "
                  "Grid steps | Bending measured / predicted (N*m) | Stretching measured / predicted (N/m) | Density |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for _, r in g.iterrows():
            yes = lambda x: "yes" if x == 1 else "no"  # noqa: E731
            lines.append(f"| {r.fabric} | {r.clips} | ({r.pred_p:g}, {r.pred_k:g}) | ({r.table2_p:g}, {r.table2_k:g}) "
                         f"| {yes(r.exact)} | {yes(r.p_match)} | {yes(r.k_match)} | {yes(r.within1)} "
                         f"| {r.class_dist:g} "
                         f"| {r.bending_N_m:.3g} / {r.pred_bending_N_m:.3g} "
                         f"| {r.stretching_N_m:.4g} / {r.pred_stretching_N_m:.4g} | {r.density_kg_m2:.3g} |")
        lines += ["", "| Score (over fabrics) | Value [95% interval] |", "|---|---|"]
        lines += [f"| {r.score} | {_fmt(r.value, r.value_lo, r.value_hi)} |" for r in match[mmask].itertuples()]
        lines += ["", "| Unit | Correlation | n | Pearson r | Spearman rho |", "|---|---|---|---|---|"]
        lines += [f"| {r.unit} | {r.description} | {r.n} | {_fmt(r.pearson, r.pearson_lo, r.pearson_hi)} "
                  f"| {_fmt(r.spearman, r.spearman_lo, r.spearman_hi)} |" for r in corr[kmask].itertuples()]
        lines.append("")
    return lines


# ------------------------------------------------------------------ entry point

# What the summary's numbers mean (measured.json "definitions").
DEFINITIONS = {
    "stretching_N_m": "mean of the low-strain row's k0 (warp), k2 (weft), k3 (shear) entries of the "
                      "fabric's stretching table (N/m); a class predicts p x the basis's value",
    "bending_N_m": "mean of the 15 bending-table entries (N*m); a class predicts k x the basis's value",
    "density_kg_m2": "the fabric's area density",
    "fabric decision": "argmax of the mean over the fabric's clips of each clip's mean sub-sequence "
                       "probabilities",
    "tables_class": "a diagnostic beside Table 2's class: the class nearest (in log space) to the fabric's "
                    "measured stretching and bending over the basis fabric's; within1_tables and "
                    "k_within1_tables score a prediction against it (both factors, and bending alone). It ignores "
                    "density: the fabric is simulated at its own, the classes at the basis's. On few fabrics a "
                    "constant answer scores these counts well too (docs/learning.md): read them beside the ranks",
    "correlations": "Pearson on raw values, Spearman on ranks; unit 'clip' resamples whole fabrics, "
                    "unit 'fabric' resamples fabrics. The fabric row 'density vs measured bending' uses no "
                    "prediction: it is how a reading that knew only each fabric's weight would rank the bending "
                    "(0.59 on the ten Table 2 fabrics), the bar a predicted bending's rank has to clear to show "
                    "that it reads more than weight",
}


def run_measured(run: Run, *, models: list | None = None, sequences: int | None = None,
                 fabrics: Sequence[str] | None = None, variant: str | None = None,
                 predictor: Predictor | None = None, activations: int = 2, progress: bool = True,
                 processes: int | None = None) -> dict:
    """Make (or reuse) the measured-fabric clips, predict them with every finished model (or ``models``),
    and write ``eval/measured.{csv,md,json}`` and ``eval/measured_correlations.csv``.

    Args:
        run: The run.
        models: The TrainedModels to predict with (default: every finished model of the run).
        sequences, fabrics, variant: Clips per fabric and setting, the fabrics and the render variant
            (default: the run's ``eval.measured_*`` settings, see ``resolve``).
        predictor: Replaces ``learn.predict.predict_clips`` (tests).
        activations: Clips whose CNN activations are drawn per model.
        progress: Print progress.
        processes: Score the models in a spawned pool of this many processes (0 or 1: in this process; default
            ``scorer_processes``); the tables are the same either way.

    Returns:
        A short summary: the variant, whether it is held out, counts, and each model's exact-match rate.

    Raises:
        ConfigError: no finished model, bad settings, or no measured clip rendered for any model's setting.
    """
    from sim.measured import clip_name, wanted_clips

    sequences, fabrics, variant = resolve(run, sequences, fabrics, variant)
    models, heldout = _models_and_heldout(run, models, variant, progress)
    t0, seconds = time.perf_counter(), {}
    with timed(seconds, "clips"):
        generation = make_clips(run, sequences, fabrics, variant, progress)
    names = [clip_name(f, n) for f, n in wanted_clips(fabrics, sequences)]
    tables, corrs, matches, entries, ensembles = [], [], [], [], []
    if processes is None:
        processes = scorer_processes(len(models))
    with timed(seconds, "predict_and_score"):
        for entry, scored in score_models(run, models, variant, names, predictor=predictor,
                                          activations=activations, progress=progress, processes=processes):
            entries.append(entry)
            if scored is not None:
                tables.append(scored[0])
                corrs.append(scored[1])
                matches.append(scored[2])
        for members in ensemble_groups([m for m, e in zip(models, entries) if "match" in e]):
            scored_ensemble = score_ensemble(run, members, variant, names)
            if scored_ensemble is not None:
                ensembles.append(scored_ensemble)
    if not tables:
        raise ConfigError(f"no measured clip was rendered for any model's setting under "
                          f"{run.measured_root / 'render' / variant}: see the render summary "
                          f"{json.dumps(generation['render'].get('failed', []))[:500]}")
    table, corr, match = _ordered(tables), _ordered(corrs), _ordered(matches)
    # The ensembles' tables apart: measured.csv keeps one row per model and fabric, its seeds numbers.
    ensemble_tables = tuple(_ordered(list(t)) for t in zip(*(e[1] for e in ensembles))) if ensembles else None
    out = run.eval_dir
    atomic_write_text(out / "measured.csv", table.to_csv(index=False, float_format="%.6g"))
    atomic_write_text(out / "measured_correlations.csv", corr.to_csv(index=False, float_format="%.6g"))
    if ensemble_tables:
        atomic_write_text(out / "measured_ensembles.csv", ensemble_tables[0].to_csv(index=False, float_format="%.6g"))
    else:
        (out / "measured_ensembles.csv").unlink(missing_ok=True)       # an earlier call's, for other models
    atomic_write_text(out / "measured.md", markdown(run, variant, heldout, table, corr, match, ensemble_tables))
    atomic_write_json(out / "measured.json", _summary(run, models, variant, heldout, fabrics, sequences,
                                                       generation, entries, [e[0] for e in ensembles],
                                                       time.perf_counter() - t0))
    return {"variant": variant, "heldout": heldout, "fabrics": len(fabrics), "sequences": sequences,
            "simulated": generation["sim"]["simulated"], "rendered": generation["render"]["rendered"],
            "predicted": sum(e["status"] == "predicted" for e in entries),
            "reused": sum(e["status"] == "reused" for e in entries),
            "seconds": {part: round(s, 1) for part, s in seconds.items()},
            "exact": {f"{e['setting']}/{e['train_variant']}/{e['model']}/s{e['seed']}":
                      next(r["value"] for r in e["match"] if r["score"] == "exact")
                      for e in entries + [e[0] for e in ensembles] if "match" in e}}


def _models_and_heldout(run: Run, models: list | None, variant: str, progress: bool) -> tuple[list, bool]:
    """The models to predict with (``models``, else every finished one) and whether ``variant`` is held out
    (neither a training variant of theirs nor a render variant of the run)."""
    models = list(models) if models is not None else finished_models(run)
    twice = sorted(k for k, n in Counter((m.setting, m.variant, m.model, m.seed) for m in models).items() if n > 1)
    if twice:
        # The tables name a model by these four; two recipes' models of one name go in two calls.
        raise ConfigError(f"two models named {'/'.join(map(str, twice[0]))} (setting/variant/model/seed) in one "
                          "measured call, e.g. from two recipes: score them in separate calls")
    if not models:
        raise ConfigError(f"no finished train folder under {run.train_root}: run `clothgap train {run.root}` "
                          "first (the measured set is predicted by the run's models)")
    heldout = variant not in ({m.variant for m in models} | set(run.config.render.variants))
    if progress and not heldout:
        print(f"[eval measured] warning: variant {variant!r} is also a training variant, so the set is not held out",
              flush=True)
    return models, heldout


def score_model(run: Run, m, variant: str, names: list[str], *, predictor: Predictor | None = None,
                activations: int = 2, progress: bool = True
                ) -> tuple[dict, tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame] | None]:
    """Predict the measured clips with model ``m`` (or reuse its finished folder) and score it.

    Returns its summary entry and its (fabric, correlation, match) tables with the model's keys, or None
    for the tables when no clip of its setting was rendered."""
    videos, status = predict_model(run, m, variant, names, predictor=predictor, activations=activations,
                                   progress=progress)
    key = _key(m.setting, m.variant, m.model, m.seed, variant)
    entry = {**_named(key), **({"recipe": m.recipe} if m.recipe else {}),
             "checkpoint": _rel(run, m.checkpoint), "status": status}
    if videos is None:
        return entry, None
    folder = model_folder(run, m, variant)
    entry.update({"folder": _rel(run, folder), "clips": len(videos), "skipped": _count_rows(folder / "skipped.csv")})
    return _scored(run, entry, key, videos, checkpoint=_rel(run, m.checkpoint), folder=_rel(run, folder))


def _key(setting: str, train_variant: str, model: str, seed, test_variant: str) -> dict:
    """A model's (or an ensemble's) ``MODEL_KEYS`` columns in its tables."""
    return dict(zip(MODEL_KEYS, (setting, train_variant, model, seed, test_variant)))


def _named(key: dict) -> dict:
    """The keys a summary entry names its model by (the tables' without the test variant)."""
    return {k: v for k, v in key.items() if k != "test_variant"}


def _scored(run: Run, entry: dict, key: dict, videos: pd.DataFrame, *, checkpoint: str, folder: str
            ) -> tuple[dict, tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]]:
    """A model's (or an ensemble's) per-clip predictions scored: its summary ``entry`` with the match rates and
    correlations added, and its (fabric, correlation, match) tables with its ``key`` columns."""
    cfg = run.config.eval

    def rng_for(*parts: str) -> np.random.Generator:
        return seeding.rng(run.config.seed, 0, seeding.EVAL, "bootstrap", "measured", key["setting"],
                           key["train_variant"], key["model"], str(key["seed"]), *parts)

    opts = {"resamples": cfg.bootstrap, "confidence": cfg.confidence, "rng_for": rng_for}
    table = fabric_table(videos)
    corr = correlation_table(videos, table, **opts)
    match = match_table(table, **opts)
    entry.update({"match": json.loads(match.to_json(orient="records")),
                  "correlations": json.loads(corr.to_json(orient="records")),
                  "per_fabric": json.loads(table.to_json(orient="records", double_precision=15))})
    return entry, (table.assign(**key, checkpoint=checkpoint, folder=folder), corr.assign(**key), match.assign(**key))


# ------------------------------------------------------------------ seeds' ensembles

def recipe_without_seeds(recipe: str) -> str:
    """A recipe's levers without its ``seeds=`` part (``camera+seeds=1`` trains the recipe ``camera`` with seed 1)
    and without ``baseline``, which changes nothing: the run's own models and ``baseline+seeds=1`` share ``""``."""
    return "+".join(p for p in recipe.split("+") if p and p != "baseline" and not p.startswith("seeds="))


def ensemble_groups(models: Sequence[TrainedModel]) -> list[list[TrainedModel]]:
    """The models that differ only in their seed (same setting, training variant, network, and recipe but for its
    ``seeds=`` part), two or more to a group, each ordered by seed."""
    groups: dict[tuple, list[TrainedModel]] = {}
    for m in models:
        groups.setdefault((m.setting, m.variant, m.model, recipe_without_seeds(m.recipe)), []).append(m)
    return [sorted(g, key=lambda m: m.seed) for g in groups.values() if len(g) >= 2]


def ensemble_label(members: Sequence[TrainedModel]) -> str:
    """An ensemble's ``seed`` in its tables: its members' seeds joined by + (``0+1``)."""
    return "+".join(str(m.seed) for m in members)


def score_ensemble(run: Run, members: Sequence[TrainedModel], variant: str, names: list[str]
                   ) -> tuple[dict, tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]] | None:
    """The members' seeds' ensemble on the measured clips: per clip the mean of the members' probabilities (each
    already the mean over the clip's sub-sequences), its class their argmax, scored like one model. Its per-clip
    predictions go to ``videos.csv`` in ``ensemble-s<seeds>`` beside the members' folders, with ``ensemble.json``
    (the members' checkpoints and their sha256). None when a member has no predictions (no clip of its setting
    rendered); only clips every member predicted count."""
    first = members[0]
    frames = []
    for m in members:
        path = model_folder(run, m, variant) / "videos.csv"
        if not path.is_file():
            return None
        frames.append(pd.read_csv(path, dtype={"video": str}).set_index("video"))
    common = sorted(set.intersection(*(set(f.index) for f in frames)))
    if not common:
        return None
    probs = np.mean([f.loc[common, preds.PROB_COLUMNS].to_numpy(float) for f in frames], axis=0)
    pred = probs.argmax(axis=1)
    videos = pd.DataFrame({"video": common, "pred": pred, "p": classes.p_value(pred), "k": classes.k_value(pred)})
    videos = pd.concat([videos, pd.DataFrame(probs, columns=preds.PROB_COLUMNS)], axis=1)
    label = ensemble_label(members)
    recipe = recipe_without_seeds(first.recipe)
    folder = model_folder(run, dataclasses.replace(first, recipe=recipe), variant).with_name(f"ensemble-s{label}")
    atomic_write_text(folder / "videos.csv", videos.to_csv(index=False, float_format="%.6g"))
    atomic_write_json(folder / "ensemble.json", {"members": [
        {"seed": m.seed, "checkpoint": _rel(run, m.checkpoint), "checkpoint_sha256": checkpoint_sha256(m)}
        for m in members], "clips": common})
    clips = _clip_fabrics(run.measured_render_dir(variant, first.setting), names)
    key = _key(first.setting, first.variant, first.model, label, variant)
    entry = {**_named(key), **({"recipe": recipe} if recipe else {}), "ensemble_of": [m.seed for m in members],
             "members": [_rel(run, m.checkpoint) for m in members], "folder": _rel(run, folder),
             "clips": len(common)}
    return _scored(run, entry, key, with_fabrics(videos, clips), folder=_rel(run, folder),
                   checkpoint=" ".join(_rel(run, m.checkpoint) for m in members))


def scorer_processes(models: int) -> int:
    """Processes to score ``models`` models in: one for every CPUS_PER_SCORER of this process's CPUs, at most one a
    model, when there are POOL_MIN_MODELS models or more on a host of POOL_MIN_CPUS or more; else 0."""
    cpus = host_processes()
    if models < POOL_MIN_MODELS or cpus < POOL_MIN_CPUS:
        return 0
    return min(models, cpus // CPUS_PER_SCORER)


def score_models(run: Run, models: list, variant: str, names: list[str], *, predictor: Predictor | None = None,
                 activations: int = 2, progress: bool = True, processes: int = 0):
    """``score_model`` of each model, in order: in this process, or in a spawned pool of ``processes`` (each with
    its share of the CPUs for torch; model i's network on visible GPU i mod their count). A ``predictor`` (a
    test's stub) keeps it in this process."""
    if processes <= 1 or len(models) < 2 or predictor is not None:
        for m in models:
            yield score_model(run, m, variant, names, predictor=predictor, activations=activations,
                              progress=progress)
        return
    score = functools.partial(_score_in_worker, run, variant=variant, names=names, activations=activations,
                              threads=max(1, host_processes() // processes))
    results = pool_map(score, models, range(len(models)), processes=processes, chunksize=1)
    for m, (entry, scored, spent) in zip(models, results):
        if progress and entry["status"] == "predicted":
            print(f"[eval measured] {m.setting}/{m.variant}/{m.model}/s{m.seed} on {variant}: "
                  f"{entry.get('clips', 0)} clips, {spent:.1f} s (one of {processes} processes)", flush=True)
        yield entry, scored


def _score_in_worker(run: Run, m, task: int, *, variant: str, names: list[str], activations: int,
                     threads: int) -> tuple[dict, tuple | None, float]:
    """``score_model`` in a pool's process (its torch limited to ``threads``, task ``task``'s network on visible
    GPU ``task`` mod their count); also its seconds. The run comes pickled with its config, whose class brings
    its own module."""
    import torch

    torch.set_num_threads(threads)
    if torch.cuda.is_available():
        torch.cuda.set_device(task % torch.cuda.device_count())
    t0 = time.perf_counter()
    entry, scored = score_model(run, m, variant, names, activations=activations, progress=False)
    return entry, scored, time.perf_counter() - t0


def _ordered(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """The models' tables as one, the model keys first."""
    frame = pd.concat(frames, ignore_index=True)
    return frame[MODEL_KEYS + [c for c in frame.columns if c not in MODEL_KEYS]]


def _summary(run: Run, models: list, variant: str, heldout: bool, fabrics: list[str], sequences: int,
             generation: dict, entries: list[dict], ensembles: list[dict], seconds: float) -> dict:
    """``eval/measured.json``: the set, the definitions, the generation summaries, every model's and every seeds'
    ensemble's entry."""
    from sim.measured import basis_values

    cfg = run.config.eval
    return {
        "variant": variant, "heldout": heldout, "training_variants": sorted({m.variant for m in models}),
        "fabrics": fabrics, "sequences": sequences, "settings": run.config.sim.settings(),
        "definitions": DEFINITIONS,
        "basis": basis_values(),
        "bootstrap": {"resamples": cfg.bootstrap, "confidence": cfg.confidence},
        "generation": generation, "models": entries, "ensembles": ensembles,
        "files": {"fabrics": "eval/measured.csv", "correlations": "eval/measured_correlations.csv",
                  **({"ensembles": "eval/measured_ensembles.csv"} if ensembles else {}),
                  "markdown": "eval/measured.md", "sim": "measured/sim", "render": f"measured/render/{variant}",
                  "per_model": f"eval/measured/{variant}"},
        "seconds": round(seconds, 2),
    }


def _rel(run: Run, path: Path) -> str:
    try:
        return str(Path(path).relative_to(run.root))
    except ValueError:
        return str(path)


def _count_rows(path: Path) -> int:
    try:
        return len(pd.read_csv(path))
    except (FileNotFoundError, pd.errors.EmptyDataError):
        return 0
