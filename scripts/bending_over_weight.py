"""How a reading of the measured fabrics ranks their bending against what the motion sees of it: the bending
table's mean B, B over the fabric's area density w (under gravity and the arm's inertia a cloth whose stiffness
and weight scale together moves the same), and the baseline that knows nothing but w.

    python3 scripts/bending_over_weight.py RUN/eval/learnability-measured.json [--out ranks.json]
    python3 scripts/bending_over_weight.py --tables [--out ranks.json]
    python3 scripts/bending_over_weight.py RUN/eval/learnability-measured.json --against BASE/eval/learnability-measured.json

Reads `clothgap eval learnability RUN --measured N`'s JSON (each classifier's per-fabric rows: predicted k, B,
w). For each classifier: Spearman of predicted k against B and against B / w, and of predicted k times w against
B (a reading corrected by the weight), and each of the last two minus the first; once: w alone against B, and
B / w against B (a perfect reader of B / w). ``--tables`` gives those two for the ten Table 2 fabrics alone, with
how many fabrics perfect readers put within one bin of Table 2 (``perfect_readers``).
Every figure resamples the same fabrics (1,000 draws, 95 % percentile intervals, seed 0), so the columns are
paired (``eval.metrics.bootstrap_correlation`` and ``bootstrap_correlation_difference``, with their rule for
resamples that have no rank); a constant reading has no rank (null). Values are kept unrounded.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.files import print_json, script_command  # noqa: E402
from eval import metrics  # noqa: E402

RESAMPLES, CONFIDENCE, SEED = 1000, 0.95, 0
SPEARMAN = {"method": "spearman", "resamples": RESAMPLES, "confidence": CONFIDENCE}


def _estimate(est: metrics.Estimate) -> dict:
    return {k: (v if math.isfinite(v) else None) for k, v in zip(("spearman", "lo", "hi"), (est.value, est.low, est.high))}


def ranks(columns: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict:
    """Each column's Spearman (x against y) with a percentile interval, and the difference of each later column
    from the first; every figure over the same resamples of fabrics (one seed), so the columns are paired."""
    out = {name: _estimate(metrics.bootstrap_correlation(x, y, rng=np.random.default_rng(SEED), **SPEARMAN))
           for name, (x, y) in columns.items()}
    first, *later = columns
    for name in later:
        out[f"{name} minus {first}"] = _estimate(metrics.bootstrap_correlation_difference(
            *columns[first], *columns[name], rng=np.random.default_rng(SEED), **SPEARMAN))
    return out


def fixed_ranks(bending: np.ndarray, weight: np.ndarray) -> dict:
    """The readings that look at no clip: the fabrics' weight alone, and their B / w read perfectly (what a reader
    of the motion could rank at best where the motion shows B / w alone)."""
    return {"fabrics": len(bending),
            "weight_alone~bending": ranks({"weight~bending": (weight, bending)})["weight~bending"],
            "bending_over_weight_alone~bending": ranks({"b_over_w~bending": (bending / weight, bending)})[
                "b_over_w~bending"]}


def table_ranks() -> dict:
    """``fixed_ranks`` of the ten Table 2 fabrics from their own tables (sim.measured), no run needed, and
    ``perfect_readers``."""
    from sim.measured import measured_values, table2_fabrics

    values = [measured_values(f) for f in table2_fabrics()]
    return {**fixed_ranks(*(np.array([v[key] for v in values]) for key in ("bending_N_m", "density_kg_m2"))),
            "perfect_readers": perfect_readers()}


def perfect_readers() -> dict:
    """How many of the ten fabrics readers that look at no clip put within one bin of (and exactly on) their Table
    2 class, goal 3's count: the class nearest to the fabric's stretching and bending over the basis's (a perfect
    reader of the tables), the one nearest to both over its weight relative to the basis's (a perfect reader of a
    motion that shows S / w and B / w alone, as a class clip, made at the basis's weight, shows S and B), and the
    constant (1, 1)."""
    from sim import classes
    from sim.measured import reference_classes

    refs = reference_classes()
    fabrics = list(refs["table2"])
    truth = list(refs["table2"].values())
    readers = {"tables": list(refs["tables"].values()), "over_weight": list(refs["over_weight"].values()),
               "constant_1_1": [classes.nearest_class(1.0, 1.0)] * len(fabrics)}
    return {name: {"within_one_bin": int(metrics.within_one_bin(truth, pred).sum()),
                   "exact": int(sum(t == p for t, p in zip(truth, pred))),
                   "classes": {f: list(classes.class_values(c)) for f, c in zip(fabrics, pred)}}
            for name, pred in readers.items()}


def setting_ranks(report: dict) -> dict:
    try:
        results = report["results"]
        first = results[0]["fabrics"]
        bending = np.array([f["bending_N_m"] for f in first], float)
        weight = np.array([f["density_kg_m2"] for f in first], float)
        readings = {r["classifier"]: np.array([f["pred_k"] for f in r["fabrics"]], float) for r in results}
        order = [f.get("fabric") for f in first]
        if any([f.get("fabric") for f in r["fabrics"]] != order for r in results):
            raise SystemExit(f"bending_over_weight: setting {report.get('setting')!r}: the classifiers list the "
                             "fabrics in different orders")
    except (KeyError, IndexError, TypeError) as e:
        raise SystemExit(f"bending_over_weight: setting {report.get('setting')!r} lacks the per-fabric rows "
                         f"(pred_k, bending_N_m, density_kg_m2): {e!r}") from e
    return {**fixed_ranks(bending, weight),
            "classifiers": {kind: ranks({"pred_k~bending": (k, bending),
                                         "pred_k~bending_over_weight": (k, bending / weight),
                                         "pred_k_times_weight~bending": (k * weight, bending)})
                            for kind, k in readings.items()}}


def _rows(report: dict) -> dict[str, list[dict]]:
    return {r["classifier"]: r["fabrics"] for r in report["results"]}


def paired_with(base: dict, report: dict) -> dict:
    """Each classifier of ``report`` against the same classifier of ``base`` (another run's reading of the same
    fabrics): its Spearman against B and against B / w minus base's, and its count within one bin of Table 2 minus
    base's, every figure over the same resamples of the fabrics."""
    out = {}
    base_rows = _rows(base)
    for kind, rows in _rows(report).items():
        if kind not in base_rows:
            continue
        old = base_rows[kind]
        if [f["fabric"] for f in old] != [f["fabric"] for f in rows]:
            raise SystemExit(f"bending_over_weight: {kind}: the two reports list different fabrics")
        bending = np.array([f["bending_N_m"] for f in rows], float)
        weight = np.array([f["density_kg_m2"] for f in rows], float)
        k_old, k_new = (np.array([f["pred_k"] for f in r], float) for r in (old, rows))
        out[kind] = {
            f"pred_k~{name} minus base": _estimate(metrics.bootstrap_correlation_difference(
                k_old, y, k_new, y, rng=np.random.default_rng(SEED), **SPEARMAN))
            for name, y in (("bending", bending), ("bending_over_weight", bending / weight))}
        within = [np.array([f["within1"] for f in r], float) for r in (old, rows)]
        fabrics = np.arange(len(rows))
        diff = metrics.bootstrap_mean_difference(within[1], fabrics, within[0], fabrics, resamples=RESAMPLES,
                                                 confidence=CONFIDENCE, rng=np.random.default_rng(SEED))
        out[kind]["within_one_bin_count minus base"] = {
            "count": round(diff.value * len(rows), 9), "lo": round(diff.low * len(rows), 9),
            "hi": round(diff.high * len(rows), 9)}
    return out


def _settings(path: Path) -> list[dict]:
    try:
        return json.loads(path.read_text())["settings"]
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"bending_over_weight: {path} is not a learnability-measured.json ({e!r})") from e


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, nargs="?", help="eval/learnability-measured.json of a run")
    ap.add_argument("--tables", action="store_true",
                    help="instead of a report: the readings that look at no clip, from the fabrics' own tables")
    ap.add_argument("--against", type=Path, metavar="BASE",
                    help="another run's learnability-measured.json of the same fabrics: each classifier's ranks "
                         "and count minus BASE's, paired by fabric")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    if args.tables == (args.report is not None):
        ap.error("give a report or --tables")
    if args.tables:
        print_json({"command": script_command(__file__, argv), "table2_fabrics": table_ranks()}, args.out)
        return
    settings = _settings(args.report)
    try:
        result = {report.get("setting", str(i)): setting_ranks(report) for i, report in enumerate(settings)}
        if args.against is not None:
            base = {r.get("setting", str(i)): r for i, r in enumerate(_settings(args.against))}
            for i, report in enumerate(settings):
                name = report.get("setting", str(i))
                if name in base:
                    result[name]["against_base"] = paired_with(base[name], report)
    except (KeyError, IndexError, TypeError) as e:
        raise SystemExit(f"bending_over_weight: the reports lack the per-fabric rows (pred_k, bending_N_m, "
                         f"density_kg_m2, within1): {e!r}") from e
    print_json({"command": script_command(__file__, argv), **result}, args.out)


if __name__ == "__main__":
    main()
