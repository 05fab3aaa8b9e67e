"""Classification metrics, correlations and bootstrap intervals for the eval stage.

Predictions arrive one row per sub-sequence (``train.clip_len`` frames), but sub-sequences of one
sequence share material, forces and texture, so they are not independent. Every
interval here therefore resamples whole SEQUENCES (``groups``), never rows: a
resample draws sequences with replacement and keeps all sub-sequences of each.

All per-row metrics (accuracy, top-k, factor accuracies, class distance) are means
of a per-row score, so a resample's value is ``sum(weights * group_sums) /
sum(weights * group_counts)``; that keeps a 1,000-resample bootstrap over a
paper-sized test set at a few milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from eval import classes


@dataclass(frozen=True)
class Estimate:
    """A point estimate with a percentile bootstrap interval."""

    value: float
    low: float
    high: float

    def as_dict(self, prefix: str) -> dict[str, float]:
        return {prefix: self.value, f"{prefix}_lo": self.low, f"{prefix}_hi": self.high}

    def fmt(self, scale: float = 1.0, digits: int = 1) -> str:
        if not np.isfinite(self.value):
            return "n/a"
        v, lo, hi = (x * scale for x in (self.value, self.low, self.high))
        if not (np.isfinite(lo) and np.isfinite(hi)):
            return f"{v:.{digits}f} [no interval]"
        return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


# ------------------------------------------------------------------ per-row scores

def _check(truth: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    truth = np.asarray(truth, dtype=np.int64)
    pred = np.asarray(pred, dtype=np.int64)
    if truth.shape != pred.shape:
        raise ValueError(f"truth and predictions differ in length: {truth.shape} vs {pred.shape}")
    for name, a in (("truth", truth), ("prediction", pred)):
        if a.size and (a.min() < 0 or a.max() >= classes.NUM_CLASSES):
            raise ValueError(f"{name} class indices must lie in 0..{classes.NUM_CLASSES - 1}, "
                             f"got {a.min()}..{a.max()}")
    return truth, pred


def correct(truth, pred) -> np.ndarray:
    truth, pred = _check(truth, pred)
    return (truth == pred).astype(float)


def topk_correct(truth, probs: np.ndarray, k: int = 3) -> np.ndarray:
    """1 where the true class is among the k most probable classes of the row."""
    probs = np.asarray(probs, dtype=float)
    truth = np.asarray(truth, dtype=np.int64)
    if probs.ndim != 2 or probs.shape[0] != truth.shape[0]:
        raise ValueError(f"probs must be (rows, classes) matching truth; got {probs.shape} for {truth.shape[0]} rows")
    top = np.argpartition(-probs, kth=min(k, probs.shape[1]) - 1, axis=1)[:, :k]
    return (top == truth[:, None]).any(axis=1).astype(float)


def stretch_correct(truth, pred) -> np.ndarray:
    """1 where the stretching factor p is right, whatever the bending factor."""
    truth, pred = _check(truth, pred)
    return (classes.p_index(truth) == classes.p_index(pred)).astype(float)


def bend_correct(truth, pred) -> np.ndarray:
    """1 where the bending factor k is right, whatever the stretching factor."""
    truth, pred = _check(truth, pred)
    return (classes.k_index(truth) == classes.k_index(pred)).astype(float)


def class_distance(truth, pred) -> np.ndarray:
    """Grid steps between classes: |dp_index| + |dk_index| (L1 on the 6 x 9 grid).

    Near misses (one step of k) then count for less than jumping across the grid,
    which plain accuracy cannot show.
    """
    truth, pred = _check(truth, pred)
    return (np.abs(classes.p_index(truth) - classes.p_index(pred))
            + np.abs(classes.k_index(truth) - classes.k_index(pred))).astype(float)


def bend_within_one(truth, pred) -> np.ndarray:
    """1 where the bending factor k is at most one bin off, whatever the stretching factor."""
    truth, pred = _check(truth, pred)
    return (np.abs(classes.k_index(truth) - classes.k_index(pred)) <= 1).astype(float)


def within_one_bin(truth, pred) -> np.ndarray:
    """1 where the prediction is at most one bin off in stretching and at most one in bending."""
    truth, pred = _check(truth, pred)
    return ((np.abs(classes.p_index(truth) - classes.p_index(pred)) <= 1)
            & (np.abs(classes.k_index(truth) - classes.k_index(pred)) <= 1)).astype(float)


def confusion_matrix(truth, pred, num_classes: int = classes.NUM_CLASSES) -> np.ndarray:
    """counts[t, p]: rows are true classes, columns predicted ones."""
    truth, pred = _check(truth, pred)
    counts = np.zeros((num_classes, num_classes), dtype=np.int64)
    np.add.at(counts, (truth, pred), 1)
    return counts


def accuracy(truth, pred) -> float:
    return float(correct(truth, pred).mean()) if len(truth) else float("nan")


def top_k_accuracy(truth, probs, k: int = 3) -> float:
    return float(topk_correct(truth, probs, k).mean()) if len(truth) else float("nan")


# ------------------------------------------------------------------ bootstrap

def group_codes(groups) -> np.ndarray:
    """Integer codes 0..G-1 for arbitrary group labels (e.g. clip ids)."""
    _, codes = np.unique(np.asarray(groups), return_inverse=True)
    return codes.reshape(-1)


def resample_weights(num_groups: int, resamples: int, rng: np.random.Generator) -> np.ndarray:
    """(resamples, groups): how often each group is drawn in each resample."""
    draws = rng.integers(0, num_groups, size=(resamples, num_groups))
    draws += np.arange(resamples)[:, None] * num_groups     # in place: one big array fewer to allocate
    return np.bincount(draws.ravel(), minlength=resamples * num_groups).reshape(resamples, num_groups)


def _interval(samples: np.ndarray, confidence: float) -> tuple[float, float]:
    samples = samples[np.isfinite(samples)]
    if samples.size == 0:
        return float("nan"), float("nan")
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(samples, [alpha, 1.0 - alpha])
    return float(lo), float(hi)


def bootstrap_mean(values, groups, *, resamples: int = 1000, confidence: float = 0.95,
                   rng: np.random.Generator | None = None) -> Estimate:
    """Mean of per-row ``values`` with an interval from resampling whole groups."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return Estimate(float("nan"), float("nan"), float("nan"))
    codes = group_codes(groups)
    if codes.shape != values.shape:
        raise ValueError(f"values and groups differ in length: {values.shape} vs {codes.shape}")
    rng = rng or np.random.default_rng(0)
    sums = np.bincount(codes, weights=values)
    counts = np.bincount(codes).astype(float)
    # As floats once, not once per product (the same products: the counts are exact in float64).
    weights = resample_weights(len(sums), resamples, rng).astype(float)
    samples = (weights @ sums) / (weights @ counts)
    return Estimate(float(values.mean()), *_interval(samples, confidence))


def bootstrap_mean_difference(values_a, groups_a, values_b, groups_b, *, resamples: int = 1000,
                              confidence: float = 0.95, rng: np.random.Generator | None = None) -> Estimate:
    """mean(a) - mean(b), PAIRED by group: one resample of group ids serves both.

    Used for domain-gap drops: the same clip id under two render variants has the
    same simulation, so pairing removes the material/motion variance from the drop.
    Groups present in only one of the two sets still take part (weight 0 on the other).
    """
    values_a, values_b = np.asarray(values_a, float), np.asarray(values_b, float)
    if values_a.size == 0 or values_b.size == 0:
        return Estimate(float("nan"), float("nan"), float("nan"))
    labels, codes = np.unique(np.concatenate([np.asarray(groups_a), np.asarray(groups_b)]), return_inverse=True)
    codes = codes.reshape(-1)
    ca, cb = codes[: len(values_a)], codes[len(values_a):]
    n = len(labels)
    sa, na = np.bincount(ca, values_a, n), np.bincount(ca, minlength=n).astype(float)
    sb, nb = np.bincount(cb, values_b, n), np.bincount(cb, minlength=n).astype(float)
    rng = rng or np.random.default_rng(0)
    weights = resample_weights(n, resamples, rng).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        samples = (weights @ sa) / (weights @ na) - (weights @ sb) / (weights @ nb)
    return Estimate(float(values_a.mean() - values_b.mean()), *_interval(samples, confidence))


# ------------------------------------------------------------------ correlations

def pearson(x, y) -> float:
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 3 or np.std(x) == 0 or np.std(y) == 0:
        return float("nan")
    return float(stats.pearsonr(x, y).statistic)


def spearman(x, y) -> float:
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return float("nan")
    return float(stats.spearmanr(x, y).statistic)


def _pearson_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Pearson r of each row pair of (R, n) float arrays, which it overwrites; nan where a row is constant."""
    # In place, one scratch array: a bootstrap's (1000, n) temporaries cost more to allocate than to fill.
    xc = np.subtract(x, x.mean(axis=1, keepdims=True), out=x)
    yc = np.subtract(y, y.mean(axis=1, keepdims=True), out=y)
    product = np.multiply(xc, xc)
    sum_xx = product.sum(axis=1)
    sum_yy = np.multiply(yc, yc, out=product).sum(axis=1)
    sum_xy = np.multiply(xc, yc, out=product).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sum_xy / np.sqrt(sum_xx * sum_yy)


def resampled_ranks(values: np.ndarray, picks: np.ndarray) -> np.ndarray:
    """``scipy.stats.rankdata(values[picks], axis=1)`` (ties averaged) for (resamples, n) ``picks``: the same floats.

    Counts each resample's rows per distinct value instead of sorting every resample: a coefficient
    of the class grid takes a few distinct values, so that is a small table.
    """
    levels, level_of = np.unique(values, return_inverse=True)
    resamples = picks.shape[0]
    if not np.isfinite(levels).all() or resamples * len(levels) > 2 ** 24:   # NaN ranks, or a table too large
        return stats.rankdata(values[picks], axis=1)
    codes = level_of.reshape(-1)[picks]
    codes += np.arange(resamples)[:, None] * len(levels)     # (resample, value) -> one code
    counts = np.bincount(codes.ravel(), minlength=resamples * len(levels)).reshape(resamples, len(levels))
    at_most = np.cumsum(counts, axis=1)                 # rows <= each value, per resample
    # The mean of the tied positions (at_most - count + 1) .. at_most: integers halved, exact in float64.
    rank_of = 0.5 * (2 * at_most - counts + 1)
    return rank_of.ravel()[codes]


def _correlation_rows(x: np.ndarray, y: np.ndarray, picks: np.ndarray, method: str) -> np.ndarray:
    """The correlation of ``x[picks[r]]`` with ``y[picks[r]]`` for every row r of (resamples, n) ``picks``
    (fresh arrays: ``_pearson_rows`` overwrites them)."""
    if method == "spearman":
        return _pearson_rows(resampled_ranks(x, picks), resampled_ranks(y, picks))
    return _pearson_rows(x[picks], y[picks])


def _correlation_interval(samples: np.ndarray, confidence: float) -> tuple[float, float]:
    """The percentile interval of resampled correlations; nan where too many resamples have none.

    A resample whose x or y is constant has no correlation. Dropping those would give the interval of
    the resamples that happen to keep the varying rows, and on ten fabrics that one model answers
    almost alike it can exclude its own point estimate. So when more resamples are undefined than
    one tail of the interval holds, there is no interval. Near that share the verdict depends on the
    resamples drawn (at 1,000 resamples the share moves by about half a point).
    """
    if np.mean(~np.isfinite(samples)) > (1.0 - confidence) / 2.0:
        return float("nan"), float("nan")
    return _interval(samples, confidence)


def bootstrap_correlation(x, y, *, method: str = "pearson", groups=None, resamples: int = 1000,
                          confidence: float = 0.95, rng: np.random.Generator | None = None) -> Estimate:
    """Correlation of x and y with a percentile interval (nan where ``_correlation_interval`` says so).

    Resamples units (rows), or whole ``groups`` when given: e.g. a fabric filmed
    under three wind strengths is one fabric, not three independent samples.
    Spearman resamples rank the resampled data again (ties averaged), so each
    resample is exactly ``scipy.stats.spearmanr`` of that resample.
    """
    if method not in ("pearson", "spearman"):
        raise ValueError(f"method must be 'pearson' or 'spearman', got {method!r}")
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in length: {x.shape} vs {y.shape}")
    point = pearson(x, y) if method == "pearson" else spearman(x, y)
    if not np.isfinite(point):
        return Estimate(point, float("nan"), float("nan"))
    rng = rng or np.random.default_rng(0)
    codes = group_codes(groups if groups is not None else np.arange(len(x)))
    sizes = np.bincount(codes)
    if (sizes == 1).all():
        picks = rng.integers(0, len(x), size=(resamples, len(x)))
        return Estimate(point, *_correlation_interval(_correlation_rows(x, y, picks, method), confidence))
    # Whole groups: one draw of group ids per resample, in that order (the intervals depend on the
    # stream). Groups may differ in size, so resamples of one length are correlated together.
    draws = np.stack([rng.integers(0, len(sizes), len(sizes)) for _ in range(resamples)])
    members = np.argsort(codes, kind="stable")          # the rows of group 0, then of group 1, ...
    if (sizes == sizes[0]).all():
        samples = _correlation_rows(x, y, members.reshape(len(sizes), -1)[draws].reshape(resamples, -1), method)
        return Estimate(point, *_correlation_interval(samples, confidence))
    rows_of = np.split(members, np.cumsum(sizes)[:-1])
    lengths = sizes[draws].sum(axis=1)
    samples = np.empty(resamples)
    for length in np.unique(lengths):
        which = np.flatnonzero(lengths == length)
        picks = np.stack([np.concatenate([rows_of[g] for g in draws[r]]) for r in which])
        samples[which] = _correlation_rows(x, y, picks, method)
    return Estimate(point, *_correlation_interval(samples, confidence))


def bootstrap_correlation_difference(x_a, y_a, x_b, y_b, *, method: str = "pearson", resamples: int = 1000,
                                     confidence: float = 0.95, rng: np.random.Generator | None = None) -> Estimate:
    """The correlation of (x_b, y_b) minus that of (x_a, y_a), two readings of the same rows, with a percentile
    interval: each resample draws the rows once for both (paired), as ``bootstrap_correlation`` draws them (the
    same ``rng`` state gives the same rows), under the same rule for resamples that have no correlation."""
    if method not in ("pearson", "spearman"):
        raise ValueError(f"method must be 'pearson' or 'spearman', got {method!r}")
    x_a, y_a, x_b, y_b = (np.asarray(v, float) for v in (x_a, y_a, x_b, y_b))
    if not x_a.shape == y_a.shape == x_b.shape == y_b.shape:
        raise ValueError(f"the readings differ in length: {x_a.shape}, {y_a.shape}, {x_b.shape}, {y_b.shape}")
    correlation = pearson if method == "pearson" else spearman
    point = correlation(x_b, y_b) - correlation(x_a, y_a)
    if not np.isfinite(point):
        return Estimate(point, float("nan"), float("nan"))
    rng = rng or np.random.default_rng(0)
    picks = rng.integers(0, len(x_a), size=(resamples, len(x_a)))
    samples = _correlation_rows(x_b, y_b, picks, method) - _correlation_rows(x_a, y_a, picks, method)
    return Estimate(point, *_correlation_interval(samples, confidence))


# ------------------------------------------------------------------ one summary

SCORES = {
    "acc": "accuracy (54 classes)",
    "top3": "top-3 accuracy",
    "stretch_acc": "stretching-factor accuracy",
    "bend_acc": "bending-factor accuracy",
    "class_dist": "mean class distance (grid steps)",
    "within1": "within one bin of stretching and of bending",
}


def row_scores(truth, pred, probs) -> dict[str, np.ndarray]:
    """Every per-row score the tables report, keyed as in ``SCORES``."""
    return {
        "acc": correct(truth, pred),
        "top3": topk_correct(truth, probs, 3),
        "stretch_acc": stretch_correct(truth, pred),
        "bend_acc": bend_correct(truth, pred),
        "class_dist": class_distance(truth, pred),
        "within1": within_one_bin(truth, pred),
    }


def summarize(truth, pred, probs, groups, *, resamples: int = 1000, confidence: float = 0.95,
              rng: np.random.Generator | None = None) -> dict[str, float]:
    """All scores with sequence-bootstrap intervals, flat (``acc``, ``acc_lo``, ``acc_hi``, ...)."""
    rng = rng or np.random.default_rng(0)
    out: dict[str, float] = {"rows": int(len(truth)), "sequences": int(len(np.unique(np.asarray(groups))))}
    for name, values in row_scores(truth, pred, probs).items():
        out.update(bootstrap_mean(values, groups, resamples=resamples, confidence=confidence, rng=rng).as_dict(name))
    return out
