"""How a reading of the measured fabrics ranks their bending against what the motion sees of it: the bending
table's mean B, B over the fabric's area density w (under gravity and the arm's inertia a cloth whose stiffness
and weight scale together moves the same), and the baseline that knows nothing but w.

    python3 scripts/bending_over_weight.py RUN/eval/learnability-measured.json [--out ranks.json]

Reads `clothgap eval learnability RUN --measured N`'s JSON (each classifier's per-fabric rows: predicted k, B,
w). For each classifier: Spearman of predicted k against B and against B / w, and of predicted k times w against
B (a reading corrected by the weight); once: w alone against B. Intervals resample fabrics (1,000, 95 %),
seeded, as the probe's own.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from eval import metrics


def rank(x, y, seed: int) -> dict:
    est = metrics.bootstrap_correlation(x, y, method="spearman", resamples=1000, confidence=0.95,
                                        rng=np.random.default_rng(seed))
    return {k: round(v, 3) for k, v in est.as_dict("spearman").items()}


def ranks(fabrics: list[dict]) -> dict:
    k = np.array([f["pred_k"] for f in fabrics], float)
    bending = np.array([f["bending_N_m"] for f in fabrics], float)
    weight = np.array([f["density_kg_m2"] for f in fabrics], float)
    return {"pred_k~bending": rank(k, bending, 0), "pred_k~bending_over_weight": rank(k, bending / weight, 1),
            "pred_k_times_weight~bending": rank(k * weight, bending, 2)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="eval/learnability-measured.json of a run")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    try:
        settings = json.loads(args.report.read_text())["settings"]
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"bending_over_weight: {args.report} is not a learnability-measured.json ({e})") from e
    result = {}
    for report in settings:
        fabrics = report["results"][0]["fabrics"]
        weight = [f["density_kg_m2"] for f in fabrics]
        result[report["setting"]] = {
            "fabrics": len(fabrics),
            "weight_alone~bending": rank(weight, [f["bending_N_m"] for f in fabrics], 3),
            "classifiers": {r["classifier"]: ranks(r["fabrics"]) for r in report["results"]}}
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
