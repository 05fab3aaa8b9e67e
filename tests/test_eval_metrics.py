"""eval.metrics: scores, sequence bootstrap, correlations against scipy."""

import numpy as np
import pytest
from scipy import stats

from eval import classes, metrics


def test_class_grid_round_trip():
    assert classes.NUM_CLASSES == 54
    assert classes.class_of(2, 0) == 18
    assert classes.p_value(18) == 2.0 and classes.k_value(18) == 0.5
    assert classes.label(53) == "p20 k20"


def test_scores_on_known_rows():
    truth = np.array([0, 9, 10, 53])
    pred = np.array([0, 10, 1, 0])          # exact, k off by 1, p off by 1, opposite corner
    assert metrics.accuracy(truth, pred) == 0.25
    np.testing.assert_array_equal(metrics.stretch_correct(truth, pred), [1, 1, 0, 0])
    np.testing.assert_array_equal(metrics.bend_correct(truth, pred), [1, 0, 1, 0])
    np.testing.assert_array_equal(metrics.class_distance(truth, pred), [0, 1, 1, 5 + 8])
    cm = metrics.confusion_matrix(truth, pred)
    assert cm.sum() == 4 and cm[53, 0] == 1 and cm[9, 10] == 1


def test_top3():
    probs = np.zeros((2, 54))
    probs[0, [5, 6, 7]] = [0.5, 0.3, 0.2]
    probs[1, [5, 6, 7, 8]] = [0.4, 0.3, 0.2, 0.1]
    np.testing.assert_array_equal(metrics.topk_correct([7, 8], probs, 3), [1, 0])


def test_bad_class_index_is_named():
    with pytest.raises(ValueError, match="0..53"):
        metrics.accuracy([0, 54], [0, 0])


def test_bootstrap_resamples_sequences_not_rows():
    # Two sequences of 50 rows each: one all right, one all wrong. A resample of
    # sequences can only give 0, 0.5 or 1; a row bootstrap would give values near 0.5.
    values = np.r_[np.ones(50), np.zeros(50)]
    groups = np.r_[["a"] * 50, ["b"] * 50]
    weights = metrics.resample_weights(2, 500, np.random.default_rng(1))
    assert (weights.sum(axis=1) == 2).all()
    est = metrics.bootstrap_mean(values, groups, resamples=500, rng=np.random.default_rng(1))
    assert est.value == 0.5
    assert est.low == 0.0 and est.high == 1.0


def test_bootstrap_interval_covers_mean_and_shrinks_with_data():
    rng = np.random.default_rng(0)
    small = metrics.bootstrap_mean(rng.random(20) < 0.6, np.arange(20), rng=np.random.default_rng(0))
    big = metrics.bootstrap_mean(rng.random(2000) < 0.6, np.arange(2000), rng=np.random.default_rng(0))
    assert small.low <= small.value <= small.high
    assert (big.high - big.low) < (small.high - small.low)


def test_paired_difference():
    groups = np.repeat(np.arange(30), 3)
    a = np.ones(90)
    b = np.r_[np.ones(45), np.zeros(45)]
    est = metrics.bootstrap_mean_difference(a, groups, b, groups, rng=np.random.default_rng(0))
    assert est.value == pytest.approx(0.5)
    assert est.low < 0.5 < est.high


def test_correlations_agree_with_scipy():
    rng = np.random.default_rng(3)
    x = rng.normal(size=40)
    y = 0.6 * x + rng.normal(size=40)
    y[:5] = np.round(y[:5])  # some ties for Spearman
    assert metrics.pearson(x, y) == pytest.approx(stats.pearsonr(x, y).statistic, abs=1e-12)
    assert metrics.spearman(x, y) == pytest.approx(stats.spearmanr(x, y).statistic, abs=1e-12)
    for method, ref in (("pearson", stats.pearsonr), ("spearman", stats.spearmanr)):
        est = metrics.bootstrap_correlation(x, y, method=method, resamples=400, rng=np.random.default_rng(0))
        assert est.value == pytest.approx(ref(x, y).statistic, abs=1e-12)
        assert -1 <= est.low < est.value < est.high <= 1


def test_bootstrap_correlation_matches_scipy_bootstrap():
    # Same percentile method, independent implementation: the intervals must be close.
    rng = np.random.default_rng(5)
    x = rng.normal(size=60)
    y = 0.5 * x + rng.normal(size=60)
    ours = metrics.bootstrap_correlation(x, y, resamples=4000, rng=np.random.default_rng(1))
    ref = stats.bootstrap((x, y), lambda a, b: stats.pearsonr(a, b).statistic, paired=True, vectorized=False,
                          n_resamples=4000, method="percentile", random_state=2).confidence_interval
    assert ours.low == pytest.approx(ref.low, abs=0.05)
    assert ours.high == pytest.approx(ref.high, abs=0.05)


def test_grouped_correlation_and_degenerate_input():
    x = np.r_[np.arange(10.0), np.arange(10.0)]
    y = x + np.r_[np.zeros(10), np.ones(10) * 0.1]
    est = metrics.bootstrap_correlation(x, y, groups=np.r_[np.arange(10), np.arange(10)], resamples=200)
    assert est.value > 0.99 and est.low > 0.9
    assert np.isnan(metrics.pearson([1, 1, 1, 1], [1, 2, 3, 4]))


def test_a_correlation_most_resamples_lack_has_no_interval():
    # Ten fabrics, a model that answers one bending for eight and a lower one for the two least stiff: a
    # resample drawing neither of the two (about one in nine) has no rank. The resamples that keep them give
    # an interval conditioned on keeping them, which on such data can leave out its own point estimate.
    measured = np.arange(10.0)
    predicted = np.r_[4.0, 4.0, np.full(8, 10.0)]
    est = metrics.bootstrap_correlation(predicted, measured, method="spearman", resamples=1000,
                                        rng=np.random.default_rng(0))
    assert est.value == pytest.approx(stats.spearmanr(predicted, measured).statistic)
    assert np.isnan(est.low) and np.isnan(est.high)
    assert est.fmt(1.0, 2) == f"{est.value:.2f} [no interval]"
    # Answers that vary keep their interval.
    varied = metrics.bootstrap_correlation(np.array([1.0, 0, 2, 3, 5, 4, 6, 7, 9, 8]), measured, method="spearman",
                                           resamples=1000, rng=np.random.default_rng(0))
    assert np.isfinite(varied.low) and varied.low < varied.value <= varied.high


def _correlation_one_by_one(x, y, groups, method, resamples, rng):
    """The grouped bootstrap the plain way: per resample, draw the groups, gather their rows, correlate."""
    codes = metrics.group_codes(groups)
    members = [np.flatnonzero(codes == g) for g in range(codes.max() + 1)]
    samples = []
    for _ in range(resamples):
        pick = np.concatenate([members[g] for g in rng.integers(0, len(members), len(members))])
        xs, ys = x[pick], y[pick]
        samples.append((stats.spearmanr if method == "spearman" else stats.pearsonr)(xs, ys).statistic
                       if np.ptp(xs) and np.ptp(ys) else np.nan)
    return np.array(samples)


@pytest.mark.parametrize("sizes", [(3,) * 8, (1, 2, 3, 4, 2, 1, 3)])
@pytest.mark.parametrize("method", ["pearson", "spearman"])
def test_grouped_correlation_is_each_resample_correlated_one_by_one(sizes, method):
    # groups of one size (gathered as one array) and of several (resamples gathered by length)
    rng = np.random.default_rng(7)
    groups = np.repeat(np.arange(len(sizes)), sizes)
    rng.shuffle(groups)
    x = np.log(rng.choice(classes.P_VALUES, len(groups)))      # few distinct values: ties
    y = x + rng.integers(0, 2, len(groups))
    est = metrics.bootstrap_correlation(x, y, method=method, groups=groups, resamples=300,
                                        rng=np.random.default_rng(3))
    samples = _correlation_one_by_one(x, y, groups, method, 300, np.random.default_rng(3))
    low, high = np.quantile(samples[np.isfinite(samples)], [0.025, 0.975])
    assert (est.low, est.high) == pytest.approx((low, high), abs=1e-12)


def test_resampled_ranks_are_scipys():
    rng = np.random.default_rng(2)
    for values in (np.log(rng.choice([0.5, 1.0, 2.0, 20.0], 30)), rng.normal(size=30),
                   np.r_[rng.integers(0, 3, 29), np.inf].astype(float)):
        picks = rng.integers(0, len(values), (50, len(values)))
        np.testing.assert_array_equal(metrics.resampled_ranks(values, picks),
                                      stats.rankdata(values[picks], axis=1))


def test_summarize_keys():
    truth = np.array([0, 0, 1, 1])
    probs = np.eye(54)[[0, 1, 1, 1]]
    out = metrics.summarize(truth, probs.argmax(1), probs, ["a", "a", "b", "b"], resamples=50)
    assert out["rows"] == 4 and out["sequences"] == 2
    assert out["acc"] == 0.75 and {"acc_lo", "top3_hi", "class_dist"} <= set(out)


@pytest.mark.parametrize("method", ["pearson", "spearman"])
def test_a_correlation_difference_is_paired_over_the_same_resampled_rows(method):
    rng = np.random.default_rng(3)
    truth = rng.normal(size=12)
    a, b = truth + rng.normal(size=12), truth + 0.3 * rng.normal(size=12)
    corr = stats.pearsonr if method == "pearson" else stats.spearmanr
    est = metrics.bootstrap_correlation_difference(a, truth, b, truth, method=method, resamples=400,
                                                   rng=np.random.default_rng(7))
    assert est.value == pytest.approx(corr(b, truth).statistic - corr(a, truth).statistic)
    # each resample's difference, one by one with scipy, over the rows bootstrap_correlation would draw
    picks = np.random.default_rng(7).integers(0, 12, size=(400, 12))
    diffs = [corr(b[p], truth[p]).statistic - corr(a[p], truth[p]).statistic for p in picks]
    assert (est.low, est.high) == pytest.approx(tuple(np.quantile(diffs, [0.025, 0.975])))
    same = metrics.bootstrap_correlation_difference(a, truth, a, truth, method=method, rng=np.random.default_rng(7))
    assert (same.value, same.low, same.high) == (0.0, 0.0, 0.0)       # a reading against itself: paired, no spread
    with pytest.raises(ValueError, match="differ in length"):
        metrics.bootstrap_correlation_difference(a, truth, b[:5], truth[:5])
