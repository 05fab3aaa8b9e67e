"""From prediction frames to the study's tables: results, Table 3, domain gap, axis ranking.

Pure functions over pandas frames (no run folders), so they are tested on small
synthetic predictions. A *cell* is one (setting, train variant, model, test
variant) with the predictions of all its training seeds stacked: seeds share the
test clips, so a sequence bootstrap over the stacked rows gives the interval of
the seed-averaged score.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pandas as pd

from eval import classes, metrics
from eval import predictions as preds
from learn.registry import MODELS

MODEL_ORDER = ("base1", "base2", "base3", "lrcn")   # the paper's column order; other models follow
MODEL_TITLES = {name: entry.title for name, entry in MODELS.items()}
ENSEMBLE_MARK = "-avg"    # a seed ensemble's model name: lrcn-avg4 is lrcn's four seeds averaged (ensemble_cells)
DETAIL_SCORES = ("top3", "stretch_acc", "bend_acc", "within1", "class_dist", "seq_acc")

# rng_for(key...) -> Generator: the stage passes clothgap.seeding-derived generators
RngFactory = Callable[..., np.random.Generator]


@dataclass
class Cell:
    setting: str
    train_variant: str
    model: str
    test_variant: str
    frame: pd.DataFrame                      # flat predictions, plus a ``seed`` column
    sources: list[str] = field(default_factory=list)   # checkpoint paths that made the rows
    seeds: str = ""                          # the seeds behind the rows, when not the frame's ``seed`` column
    # (frame, its seed_sequences): made once for the scores and the correlations, again if the frame is replaced
    _sequences: tuple[pd.DataFrame, pd.DataFrame] | None = field(default=None, repr=False, compare=False)

    @property
    def key(self) -> tuple[str, str, str, str]:
        return (self.setting, self.train_variant, self.model, self.test_variant)

    def sequences(self) -> pd.DataFrame:
        """One row per (seed, test clip): the clip's video-level decision (``preds.seed_sequences``)."""
        if self._sequences is None or self._sequences[0] is not self.frame:
            self._sequences = (self.frame, preds.seed_sequences(self.frame))
        return self._sequences[1]


def split_setting(setting: str) -> tuple[str, str]:
    """'wind-uniform1' -> ('wind', 'uniform1')."""
    motion, _, remeshing = setting.partition("-")
    return motion, remeshing or "?"


def model_title(model: str) -> str:
    """The model's title in tables and the report (a seed ensemble: its model's, and how many seeds)."""
    base, mark, n = model.partition(ENSEMBLE_MARK)
    title = MODEL_TITLES.get(base, base)
    return f"{title}, {n} seeds averaged" if mark else title


def model_sort_key(model: str) -> tuple[int, str]:
    """The paper's order; a seed ensemble (``lrcn-avg4``) right after its model, other models last."""
    base = model.partition(ENSEMBLE_MARK)[0]
    return (MODEL_ORDER.index(base) if base in MODEL_ORDER else len(MODEL_ORDER), model)


def score_cell(cell: Cell, *, resamples: int, confidence: float, rng: np.random.Generator) -> dict:
    """Every score of one cell with sequence-bootstrap intervals, plus sequence-level accuracy."""
    frame = cell.frame
    probs = preds.probs_of(frame)
    groups = frame["clip_id"].to_numpy()
    out = metrics.summarize(frame["class_index"].to_numpy(), frame["pred"].to_numpy(), probs, groups,
                            resamples=resamples, confidence=confidence, rng=rng)
    # One decision per (seed, clip): mean probabilities over that clip's sub-sequences.
    out.update(metrics.bootstrap_mean(*preds.decisions_correct(cell.sequences()), resamples=resamples,
                                      confidence=confidence, rng=rng).as_dict("seq_acc"))
    return out


def results_frame(cells: list[Cell], *, resamples: int, confidence: float, rng_for: RngFactory) -> pd.DataFrame:
    """One row per cell: identity, provenance and every score."""
    rows = []
    for cell in cells:
        motion, remeshing = split_setting(cell.setting)
        row = {"setting": cell.setting, "motion": motion, "remeshing": remeshing,
               "train_variant": cell.train_variant, "model": cell.model, "test_variant": cell.test_variant,
               "in_domain": cell.train_variant == cell.test_variant,
               "seeds": cell.seeds or " ".join(str(s) for s in sorted(cell.frame["seed"].unique()))}
        row.update(score_cell(cell, resamples=resamples, confidence=confidence, rng=rng_for("score", *cell.key)))
        row["checkpoints"] = " ".join(cell.sources)
        rows.append(row)
    return pd.DataFrame(rows)


def ensemble_cells(cells) -> list[Cell]:
    """For each cell of two or more seeds, the cell of their ensemble (``preds.seed_average``, model
    ``<model>-avg<N>``). It is one model, so its interval is over sequences alone."""
    out = []
    for cell in cells:
        seeds = sorted(int(s) for s in cell.frame["seed"].unique())
        if len(seeds) < 2:
            continue
        out.append(Cell(cell.setting, cell.train_variant, f"{cell.model}{ENSEMBLE_MARK}{len(seeds)}",
                        cell.test_variant, frame=preds.seed_average(cell.frame).assign(seed=seeds[0]),
                        sources=list(cell.sources), seeds=" ".join(map(str, seeds))))
    return out


# ------------------------------------------------------------------ Table 3

def table3(results: pd.DataFrame, texture_of: dict[str, str]) -> pd.DataFrame:
    """The paper's Table 3 shape: rows motion x remeshing x texture, columns per model.

    Only in-domain cells (trained and tested on the same variant) belong here, as
    in the paper; cross-variant results are the domain-gap table's job. A variant
    column is kept because two variants may share a texture family.
    """
    cols = ["motion", "remeshing", "texture", "variant"]
    inside = results[results["in_domain"]]
    if inside.empty:
        return pd.DataFrame(columns=cols)
    rows: dict[tuple, dict] = {}
    for _, r in inside.iterrows():
        key = (r["motion"], r["remeshing"], texture_of.get(r["train_variant"], r["train_variant"]), r["train_variant"])
        row = rows.setdefault(key, dict(zip(cols, key)))
        m = r["model"]
        for score in ("acc", *DETAIL_SCORES):
            for suffix in ("", "_lo", "_hi"):
                row[f"{m}_{score}{suffix}"] = r[f"{score}{suffix}"]
        row[f"{m}_sequences"] = r["sequences"]
        row[f"{m}_seeds"] = r["seeds"]
        row[f"{m}_checkpoints"] = r["checkpoints"]
    table = pd.DataFrame(list(rows.values()))
    models = sorted(inside["model"].unique(), key=model_sort_key)
    ordered = cols + [c for m in models for c in table.columns if c.startswith(f"{m}_")]
    return table[ordered].sort_values(cols, ignore_index=True)


def table3_models(table: pd.DataFrame) -> list[str]:
    return sorted({c[: -len("_acc")] for c in table.columns if c.endswith("_acc")
                   and not c.endswith(("_seq_acc", "_stretch_acc", "_bend_acc"))}, key=model_sort_key)


def _pct(row, prefix: str) -> str:
    return metrics.Estimate(row[prefix], row[f"{prefix}_lo"], row[f"{prefix}_hi"]).fmt(100.0)


def table3_markdown(table: pd.DataFrame) -> str:
    """Accuracy per model (%, 95% sequence-bootstrap interval), then a detail table per model."""
    if table.empty:
        return "No in-domain results: no model was both trained and tested on one variant.\n"
    models = table3_models(table)
    head = ["Motion", "Re-mesh", "Texture", "Variant"] + [model_title(m) for m in models]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for _, r in table.iterrows():
        cells = [r["motion"], r["remeshing"], r["texture"], r["variant"]]
        cells += [_pct(r, f"{m}_acc") if pd.notna(r.get(f"{m}_acc")) else "" for m in models]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    out = ["Accuracy over 54 classes, % of test sub-sequences (train.clip_len frames each), with a 95% interval from "
           "resampling test sequences.", "", *lines, ""]
    detail_head = ["Motion", "Re-mesh", "Texture", "Variant", "Top-3 %", "Stretch-factor %", "Bend-factor %",
                   "Class distance (grid steps)", "Per-video %", "Test sequences", "Seeds", "Checkpoint(s)"]
    for m in models:
        out += [f"Details: {model_title(m)}", "", "| " + " | ".join(detail_head) + " |",
                "|" + "---|" * len(detail_head)]
        for _, r in table.iterrows():
            if pd.isna(r.get(f"{m}_acc")):
                continue
            cells = [r["motion"], r["remeshing"], r["texture"], r["variant"],
                     _pct(r, f"{m}_top3"), _pct(r, f"{m}_stretch_acc"), _pct(r, f"{m}_bend_acc"),
                     metrics.Estimate(r[f"{m}_class_dist"], r[f"{m}_class_dist_lo"],
                                      r[f"{m}_class_dist_hi"]).fmt(1.0, 2),
                     _pct(r, f"{m}_seq_acc"), int(r[f"{m}_sequences"]), r[f"{m}_seeds"],
                     f"`{r[f'{m}_checkpoints']}`"]
            out.append("| " + " | ".join(str(c) for c in cells) + " |")
        out.append("")
    return "\n".join(out)


# ------------------------------------------------------------------ domain gap

def domain_gap(cells: dict[tuple, Cell], results: pd.DataFrame, *, resamples: int, confidence: float,
               rng_for: RngFactory, reference: str | None = None) -> pd.DataFrame:
    """Accuracy and correlation for every (train variant, test variant) pair and its drops, paired by clip.

    ``drop`` = acc(trained on A, tested on A) - acc(A on B): what leaving the
    training domain costs. ``gap`` = acc(B on B) - acc(A on B): how far A's model
    stays from one trained in the test domain itself (the sim-to-"real" gap when B
    stands in for reality). ``gain`` = acc(A on B) - acc(R on B), R the ``reference``
    training variant (a study's `paper`): what training on A instead of R buys on B,
    e.g. on a held-out look no model trains on. On in-domain rows ``in_domain_gain`` = acc(A on A) -
    acc(R on R): which look is easier to learn and read. The intervals resample clip ids jointly for
    the two terms, since the same clip id has the same simulation under every variant.
    ``p_spearman``, ``p_pearson``, ``k_spearman``, ``k_pearson`` (each with ``_lo``/``_hi``):
    how the predicted class's stiffness coefficients follow the true ones
    (``coefficient_correlations``).
    """
    rows = []
    for _, r in results.iterrows():
        s, a, m, b = r["setting"], r["train_variant"], r["model"], r["test_variant"]
        cell = cells[(s, a, m, b)]
        own, target = cells.get((s, a, m, a)), cells.get((s, b, m, b))
        baseline = cells.get((s, reference, m, b)) if reference is not None else None
        # in its own domain against the reference in its own: which look is easier to read
        own_baseline = cells.get((s, reference, m, reference)) if reference is not None and a == b else None
        # name: (minuend, subtrahend, the reference cell of the two, which may be missing)
        differences = {"drop": (own, cell, own), "gap": (target, cell, target), "gain": (cell, baseline, baseline),
                       "in_domain_gain": (cell, own_baseline, own_baseline)}
        row = {k: r[k] for k in ("setting", "model", "train_variant", "test_variant", "in_domain", "seeds",
                                 "sequences", "acc", "acc_lo", "acc_hi")}
        for name, (first, second, ref) in differences.items():
            if ref is None:
                est = metrics.Estimate(float("nan"), float("nan"), float("nan"))
            else:
                est = metrics.bootstrap_mean_difference(
                    metrics.correct(first.frame["class_index"], first.frame["pred"]), first.frame["clip_id"],
                    metrics.correct(second.frame["class_index"], second.frame["pred"]), second.frame["clip_id"],
                    resamples=resamples, confidence=confidence, rng=rng_for(name, s, a, m, b))
            row[f"{name}_reference_acc"] = (metrics.accuracy(ref.frame["class_index"], ref.frame["pred"])
                                            if ref is not None else float("nan"))
            row.update(est.as_dict(name))
        row.update(coefficient_correlations(cell, resamples=resamples, confidence=confidence,
                                            rng_for=lambda *k, key=(s, a, m, b): rng_for("corr", *key, *k)))
        row["checkpoints"] = r["checkpoints"]
        rows.append(row)
    return pd.DataFrame(rows)


CORRELATION_COLUMNS = tuple(f"{coef}_{method}" for coef in ("p", "k") for method in ("spearman", "pearson"))


def coefficient_correlations(cell: Cell, *, resamples: int, confidence: float, rng_for: RngFactory) -> dict:
    """Correlation of the predicted class's stiffness coefficients with the true class's, on one cell.

    One decision per (seed, test sequence): the argmax of its mean sub-sequence
    probabilities. ``p_*`` correlates predicted with true stretching factor p,
    ``k_*`` bending factor k; Spearman on ranks, Pearson on log coefficients (the
    grid is geometric, 0.5 .. 20). Intervals resample sequences (all seeds of a
    sequence together). NaN where either side is constant.
    """
    seq = cell.sequences()
    groups = seq["clip_id"].to_numpy()
    out: dict[str, float] = {}
    for coef, value in (("p", classes.p_value), ("k", classes.k_value)):
        true = np.log(value(seq["class_index"].to_numpy()))
        pred = np.log(value(seq["pred"].to_numpy()))
        for method in ("spearman", "pearson"):
            est = metrics.bootstrap_correlation(pred, true, method=method, groups=groups, resamples=resamples,
                                                confidence=confidence, rng=rng_for(coef, method))
            out.update(est.as_dict(f"{coef}_{method}"))
    return out


def gap_matrix(gap: pd.DataFrame, setting: str, model: str) -> pd.DataFrame:
    """Accuracy matrix: rows train variant, columns test variant."""
    sub = gap[(gap["setting"] == setting) & (gap["model"] == model)]
    return sub.pivot(index="train_variant", columns="test_variant", values="acc")


# ------------------------------------------------------------------ render axes

def differing_axes(variant_settings: dict[str, dict]) -> list[str]:
    """Settings whose value is not the same in every variant."""
    keys = sorted({k for s in variant_settings.values() for k in s})
    return [k for k in keys if len({repr(s.get(k)) for s in variant_settings.values()}) > 1]


def axis_groups(variant_settings: dict[str, dict]) -> dict[str, list[str]]:
    """The differing settings as axes: settings that split the variants the same way (every variant that changes
    one changes the others, e.g. a camera variant's exposure, noise and vignetting) are one axis, named by its
    settings joined with ``+``, since no pair of these variants can tell them apart."""
    names = sorted(variant_settings)
    groups: dict[tuple, list[str]] = {}
    for key in differing_axes(variant_settings):
        values = [repr(variant_settings[v].get(key)) for v in names]
        partition = tuple(values.index(x) for x in values)     # which variants share a value, not the values
        groups.setdefault(partition, []).append(key)
    return {"+".join(keys): keys for keys in groups.values()}


def rank_axes(gap: pd.DataFrame, variant_settings: dict[str, dict], cells: dict[tuple, Cell] | None = None, *,
              resamples: int = 1000, confidence: float = 0.95, rng: np.random.Generator | None = None) -> pd.DataFrame:
    """Which render axis closes most of the gap to a test variant. An axis is a setting, or settings that the
    variants only ever change together (``axis_groups``).

    For a test variant T and two training variants A, B where B agrees with T on
    axis x and A does not, ``acc(B on T) - acc(A on T)`` is what moving x to T's
    value bought. Pairs that differ ONLY in x measure x alone (``clean``); pairs
    that differ in more axes are confounded and count only when an axis has no
    clean pair. ``share`` is that gain over A's gap to T (1 = all of it).
    Ranked by mean gain, largest first. With the ``cells`` (key ``(setting, train
    variant, model, test variant)``), ``mean_gain_lo``/``_hi`` is its interval from
    resampling test clips, one draw of (setting, clip) for every pair at once: the
    same clip has the same simulation under every variant.
    """
    groups = axis_groups(variant_settings)
    # a group's settings split the variants alike, so its first setting says where every one of them differs
    axes = list(groups)
    first = {axis: keys[0] for axis, keys in groups.items()}
    cols = ["axis", "mean_gain", "mean_gain_lo", "mean_gain_hi", "mean_share", "pairs", "clean", "examples"]
    if len(variant_settings) < 2 or not axes or gap.empty:
        return pd.DataFrame(columns=cols)
    acc = {(r.setting, r.model, r.train_variant, r.test_variant): r.acc for r in gap.itertuples()}
    evidence: dict[str, dict[bool, list]] = {x: {True: [], False: []} for x in axes}
    for (s, m, a, t), acc_a in acc.items():
        if t not in variant_settings or a not in variant_settings or a == t:
            continue
        gap_a = acc.get((s, m, t, t), np.nan) - acc_a
        for b in variant_settings:
            acc_b = acc.get((s, m, b, t))
            if b == a or acc_b is None:
                continue
            va, vb, vt = variant_settings[a], variant_settings[b], variant_settings[t]
            diff = [x for x in axes if repr(va.get(first[x])) != repr(vb.get(first[x]))]
            for x in diff:
                k = first[x]
                if repr(vb.get(k)) == repr(vt.get(k)) != repr(va.get(k)):
                    gain = acc_b - acc_a
                    share = gain / gap_a if np.isfinite(gap_a) and gap_a > 0 else np.nan
                    evidence[x][diff == [x]].append((gain, share, f"{s}/{m}: {a}->{b} on {t}",
                                                     ((s, a, m, t), (s, b, m, t))))
    resampled = _ResampledAccuracy(cells, resamples, rng) if cells else None
    rows = []
    for x in axes:
        clean = bool(evidence[x][True])
        items = evidence[x][True] or evidence[x][False]
        if not items:
            continue
        gains, shares, names, keys = zip(*items)
        low = high = np.nan
        if resampled is not None and all(k in cells for pair in keys for k in pair):
            samples = np.mean([resampled(kb) - resampled(ka) for ka, kb in keys], axis=0)
            low, high = metrics._interval(samples, confidence)
        rows.append({"axis": x, "mean_gain": float(np.mean(gains)), "mean_gain_lo": low, "mean_gain_hi": high,
                     "mean_share": float(np.nanmean(shares)) if np.isfinite(shares).any() else np.nan,
                     "pairs": len(items), "clean": clean, "examples": "; ".join(names[:3])})
    return pd.DataFrame(rows, columns=cols).sort_values("mean_gain", ascending=False, ignore_index=True)


class _ResampledAccuracy:
    """Each cell's accuracy under the same bootstrap draws of (setting, clip id): ``(resamples,)`` per cell."""

    def __init__(self, cells: dict[tuple, Cell], resamples: int, rng: np.random.Generator | None):
        self.cells = cells
        labels = sorted({(k[0], c) for k, cell in cells.items() for c in cell.frame["clip_id"]})
        self.code = {label: i for i, label in enumerate(labels)}
        self.weights = metrics.resample_weights(len(labels), resamples, rng or np.random.default_rng(0))
        self.done: dict[tuple, np.ndarray] = {}

    def __call__(self, key: tuple) -> np.ndarray:
        if key not in self.done:
            frame = self.cells[key].frame
            codes = np.array([self.code[(key[0], c)] for c in frame["clip_id"]], np.int64)
            n = len(self.code)
            hits = np.bincount(codes, metrics.correct(frame["class_index"], frame["pred"]), n)
            with np.errstate(invalid="ignore", divide="ignore"):
                self.done[key] = (self.weights @ hits) / (self.weights @ np.bincount(codes, minlength=n))
        return self.done[key]
