"""How far, and which way, readings of the measured fabrics sit from what a motion that shows S / w and B / w alone
would tell (gravity and the arm's inertia scale with the weight; the classes are made at the basis's weight): per
reading, the mean over fabrics of log(predicted k / k_w), where k_w = (B / B_basis) / (w / w_basis) is the fabric's
bending over its weight relative to the basis's, not rounded to a class (the bias: below zero reads the bending
low), the mean of its absolute value (how far fabric by fabric), and the same for p against (S / S_basis) / (w /
w_basis). Neighbouring classes are 0.22-0.69 of log apart in k, 0.41-1.20 in p.

    python3 scripts/reading_bias.py FILE[:KEY/KEY...] [...] [--pair A,B ...] [--out bias.json]

FILE is JSON; the keys lead inside it to ``clothgap eval measured``'s JSON (its models' and ensembles'
``per_fabric`` rows, each reading named as the Markdown names its section; a results file's ``measured`` look), to
a results file's ``measured_fabrics`` look (``{model: [rows with "Fabric" and "Predicted (p, k)"]}``, as
``scripts/gather_lease.py`` keeps the Markdown's tables of a JSON without per-fabric rows) or to a ``clothgap eval
learnability --measured`` report (``{"settings": [{"results": [{"classifier", "fabrics": [{"fabric", "pred_p",
"pred_k"}]}]}]}``) or to scripts/reader_ceiling.py's output (``{"measured": {"rows": [{"fabric", "pred"}]}}``).
Each figure has a 95 % interval from resampling the fabrics (1,000 draws, seed 0).
``--pair A,B`` (two of the inputs, as given) pairs each reading of B with A's reading of the same name (a classifier,
or a model) and gives B's bias minus A's, over the same resamples of the fabrics both read. A file, key or row that
does not hold readings of known fabrics is named and nothing is written.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.files import print_json, script_command  # noqa: E402
from eval import metrics  # noqa: E402

RESAMPLES, SEED = 1000, 0


def readings(doc) -> dict[str, dict[str, tuple[float, float]]]:
    """{reading name: {fabric: (predicted p, predicted k)}} from a measured-fabrics look or a probe report."""
    if isinstance(doc, dict) and "fabrics" in doc and "models" in doc:
        # `clothgap eval measured`'s JSON, each reading named as its Markdown's section is (measured_fabrics' keys)
        from eval.measured import reading_title

        rows = {}
        for kind in ("models", "ensembles"):
            for m in doc.get(kind) or []:
                name = reading_title(m["model"], m["train_variant"], m["setting"], m["seed"], kind == "ensembles")
                if "per_fabric" in m:
                    rows[name] = [(f["fabric"], f["pred_p"], f["pred_k"]) for f in m["per_fabric"]]
                elif m.get("status") not in (None, "predicted", "reused"):
                    continue        # not scored (e.g. no rendered clips), and left out of the Markdown alike
                else:
                    raise ValueError(f"{name}: no per-fabric rows, as in a file written before they were kept "
                                     "(read its measured_fabrics tables instead)")
    elif isinstance(doc, dict) and isinstance(doc.get("measured"), dict) and "rows" in doc["measured"]:
        # scripts/reader_ceiling.py's output: its reader on the measured fabrics' true lattices, a class index each
        from eval import classes

        seed = f", seed {doc['seed']}" if "seed" in doc else ""
        name = f"{doc.get('reader', 'frames')} reader on true lattices ({doc['setting']}, {doc['clips']} clips{seed})"
        rows = {name: [(r["fabric"], float(classes.p_value(r["pred"])), float(classes.k_value(r["pred"])))
                       for r in doc["measured"]["rows"]]}
    elif isinstance(doc, dict) and "settings" in doc:
        rows = {f"{s.get('setting', i)} {r['classifier']}": [(f["fabric"], f["pred_p"], f["pred_k"])
                                                             for f in r["fabrics"]]
                for i, s in enumerate(doc["settings"]) for r in s["results"]}
    elif isinstance(doc, dict) and doc and all(isinstance(v, list) for v in doc.values()):
        rows = {}
        for model, table in doc.items():
            rows[model] = []
            for row in table:
                numbers = re.findall(r"[0-9]+(?:\.[0-9]+)?", row["Predicted (p, k)"])
                if len(numbers) != 2:
                    raise ValueError(f"{model}: {row['Predicted (p, k)']!r} is not '(p, k)'")
                rows[model].append((row["Fabric"], *numbers))
    else:
        raise ValueError("neither a measured-fabrics look (JSON or its tables), a learnability-measured report nor "
                         "a reader_ceiling output")
    if not rows:
        raise ValueError("it holds no reading")
    out = {}
    for name, found in rows.items():
        fabrics = [f for f, _, _ in found]
        if len(set(fabrics)) != len(fabrics):
            raise ValueError(f"{name}: a fabric read twice")
        out[name] = {f: (float(p), float(k)) for f, p, k in found}
        if not all(v > 0 for pk in out[name].values() for v in pk):
            raise ValueError(f"{name}: a predicted p or k that is not positive")
    return out


def input_readings(item: str) -> dict[str, dict[str, tuple[float, float]]]:
    """The readings (``readings``) of one input, ``FILE[:KEY/KEY...]``: the JSON file, the keys followed into it."""
    path, _, keys = item.partition(":")
    doc = json.loads(Path(path).read_text())
    for key in filter(None, keys.split("/")):
        doc = doc[key]
    return readings(doc)


def log_ratios(reading: dict[str, tuple[float, float]]) -> dict[str, dict[str, float]]:
    """{"p": {fabric: log(pred p / p_w)}, "k": ...}: each fabric's reading against its S / w and B / w
    (``sim.measured.over_weight_ratios``)."""
    from sim.measured import over_weight_ratios

    out: dict[str, dict[str, float]] = {"p": {}, "k": {}}
    for fabric, (pred_p, pred_k) in reading.items():
        p_w, k_w = over_weight_ratios(fabric)
        out["p"][fabric], out["k"][fabric] = math.log(pred_p / p_w), math.log(pred_k / k_w)
    return out


def _estimate(est: metrics.Estimate) -> dict:
    return {"value": est.value, "lo": est.low, "hi": est.high}


def bias(logs: dict[str, dict[str, float]]) -> dict:
    """A reading's mean log ratios (``log_ratios``; signed and absolute) over its fabrics, each with its interval."""
    out: dict = {"fabrics": len(logs["k"])}
    for axis, by_fabric in logs.items():
        x = np.array(list(by_fabric.values()))
        groups = np.arange(len(x))
        for name, values in (("bias", x), ("mean_abs", np.abs(x))):
            out[f"{axis}_{name}"] = _estimate(metrics.bootstrap_mean(values, groups, resamples=RESAMPLES,
                                                                    rng=np.random.default_rng(SEED)))
    return out


def paired(la: dict[str, dict[str, float]], lb: dict[str, dict[str, float]]) -> dict:
    """B's biases minus A's (``log_ratios`` of each) over the fabrics both read, the fabrics resampled once for
    both."""
    common = [f for f in la["k"] if f in lb["k"]]
    if not common:
        raise ValueError("no fabric read by both")
    out: dict = {"fabrics": len(common)}
    groups = np.arange(len(common))
    for axis in ("p", "k"):
        xa, xb = (np.array([logs[axis][f] for f in common]) for logs in (la, lb))
        for name, fa, fb in (("bias", xa, xb), ("mean_abs", np.abs(xa), np.abs(xb))):
            out[f"{axis}_{name}"] = _estimate(metrics.bootstrap_mean_difference(
                fb, groups, fa, groups, resamples=RESAMPLES, rng=np.random.default_rng(SEED)))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", metavar="FILE[:KEY/KEY...]")
    ap.add_argument("--pair", action="append", default=[], metavar="A,B",
                    help="two of the inputs: each reading of B against A's reading of the same name")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    found: dict[str, dict] = {}
    result: dict = {"command": script_command(__file__, argv), "readings": {}, "pairs": {}}
    for item in args.inputs:
        try:
            # each reading's log ratios, once (an unknown fabric: sim.materials' KeyError names it)
            found[item] = {name: log_ratios(reading) for name, reading in input_readings(item).items()}
            for name, logs in found[item].items():
                result["readings"][f"{item} {name}"] = bias(logs)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SystemExit(f"reading_bias: {item}: {e}") from e
    for pair in args.pair:
        a, _, b = pair.partition(",")
        if a not in found or b not in found:
            raise SystemExit(f"reading_bias: --pair {pair}: give two of the inputs, as written, split by a comma")
        if not set(found[a]) & set(found[b]):
            raise SystemExit(f"reading_bias: --pair {pair}: no reading of the second has a name the first's have "
                             f"(first: {', '.join(sorted(found[a]))})")
        for name, logs in found[b].items():
            if name in found[a]:
                try:
                    result["pairs"][f"{b} minus {a}: {name}"] = paired(found[a][name], logs)
                except ValueError as e:
                    raise SystemExit(f"reading_bias: --pair {pair}: {name}: {e}") from e
    print_json(result, args.out)


if __name__ == "__main__":
    main()
