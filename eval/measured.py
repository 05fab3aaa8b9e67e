"""Measured fabrics: the ten Wang et al. 2011 fabrics, simulated with their own tables and
rendered in a held-out variant, as a ground-truth check between simulation and reality.

Input is a folder of rendered clips in the render contract (``<clip>/ldr/%04d.png``,
``meta.json``, ``DONE``) whose meta names the fabric in ``fabric`` (or
``material``); the simulation and rendering that make them belong to the sim and
render stages. For each fabric the clips' sub-sequence probabilities are averaged
into one predicted class, which is compared with the class the paper assigns it
in Table 2, and the per-clip predictions are correlated with the fabric's
measured bending stiffness and density through the same code as real videos
(``eval.real.table4``; the bootstrap resamples fabrics, not clips).

Outputs in OUT: ``fabrics.csv`` (per fabric: prediction, Table 2 class, matches),
``match.csv`` (match rates with intervals over fabrics), ``correlations.csv``
(Table 4 shape, plus predicted p, k against the paper's estimated ratios),
``measured.md``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from clothgap.errors import MissingInputError
from clothgap.runs import atomic_write_text, is_done
from clothgap.seeding import stream_id
from eval import classes, metrics, real
from eval import predictions as preds

# Yang, Liang, Lin 2017, Table 2: estimated ratios to the basis (p~, k~) and the
# sub-space class (p, k) the paper maps each measured fabric to.
TABLE2: dict[str, tuple[float, float, float, float]] = {
    "ivory-rib-knit": (1.3817, 2.3, 1, 2),
    "pink-ribbon-brown": (2.9343, 12, 3, 10),
    "camel-ponte-roma": (1, 0.52, 1, 0.5),
    "white-dots-on-blk": (15.8108, 3.5, 20, 4),
    "navy-sparkle-sweat": (0.5613, 1.7, 0.5, 2),
    "gray-interlock": (1.0164, 1.6, 1, 2),
    "11oz-black-denim": (3.6079, 3, 3, 3),
    "white-swim-solid": (1.9126, 2.9, 2, 3),
    "tango-red-jet-set": (1.9784, 1.9, 2, 2),
    "royal-target": (22.2857, 19, 20, 20),
}
FABRIC_KEYS = ("fabric", "material")

Predictor = Callable[[Path, list[Path]], pd.DataFrame]


def table2_class(fabric: str) -> int:
    p_est, k_est, p, k = TABLE2[fabric]
    return classes.class_of(classes.P_VALUES.index(p), classes.K_VALUES.index(k))


def measured_values(fabric: str) -> dict[str, float]:
    """Mean bending entry (N*m) and area density (kg/m^2) of a fabric's measured table."""
    from sim.materials import load_material

    m = load_material(fabric)
    return {"stiffness": float(np.mean(m.bending)), "density": float(m.density)}


def fabric_clips(clips_dir: Path) -> dict[Path, str]:
    """Finished clip folders and the fabric each one names."""
    if not clips_dir.is_dir():
        raise MissingInputError(f"clip folder {clips_dir} does not exist")
    found = {}
    for folder in sorted(p for p in clips_dir.iterdir() if p.is_dir() and is_done(p)):
        meta = json.loads((folder / "meta.json").read_text())
        name = next((meta[k] for k in FABRIC_KEYS if isinstance(meta.get(k), str)), None)
        if name is None:
            raise ValueError(f"{folder / 'meta.json'} names no fabric (expected a key {' or '.join(FABRIC_KEYS)})")
        found[folder] = name
    if not found:
        raise ValueError(f"no finished clip folders (with DONE) in {clips_dir}")
    return found


def _default_predictor(train_dir: Path, clip_dirs: list[Path]) -> pd.DataFrame:
    from learn.predict import predict_clips

    return predict_clips(train_dir, clip_dirs)


def compare_with_table2(per_clip: pd.DataFrame) -> pd.DataFrame:
    """One row per fabric: the class from its clips' mean probabilities against Table 2's."""
    rows = []
    for fabric, g in per_clip.groupby("fabric", sort=True):
        pred = int(g[preds.PROB_COLUMNS].to_numpy().mean(axis=0).argmax())
        row = {"fabric": fabric, "clips": len(g), "pred": pred, "pred_p": float(classes.p_value(pred)),
               "pred_k": float(classes.k_value(pred))}
        if fabric in TABLE2:
            p_est, k_est, p, k = TABLE2[fabric]
            truth = table2_class(fabric)
            row.update({"table2_p_est": p_est, "table2_k_est": k_est, "table2_p": p, "table2_k": k,
                        "table2_class": truth, "exact": float(pred == truth),
                        "p_match": float(metrics.stretch_correct([truth], [pred])[0]),
                        "k_match": float(metrics.bend_correct([truth], [pred])[0]),
                        "class_dist": float(metrics.class_distance([truth], [pred])[0])})
        rows.append(row)
    return pd.DataFrame(rows)


def evaluate_measured(clips_dir: Path | str, train_dir: Path | str, out_dir: Path | str, *,
                      resamples: int = 1000, confidence: float = 0.95, seed: int = 0,
                      predictor: Predictor | None = None, truth: Callable[[str], dict] = measured_values) -> Path:
    """Predict the measured-fabric clips in ``clips_dir``; returns ``fabrics.csv``'s path.

    ``truth(fabric)`` gives ``{"stiffness", "density"}`` (default: the fabric's
    table in assets/materials); ``predictor`` replaces predict_clips (tests).
    """
    clips_dir, train_dir, out_dir = map(Path, (clips_dir, train_dir, out_dir))
    named = fabric_clips(clips_dir)
    frame = preds.to_flat((predictor or _default_predictor)(train_dir, list(named)))
    clip_fabric = {json.loads((d / "meta.json").read_text()).get("clip_id", d.name): f for d, f in named.items()}
    per_clip = preds.per_sequence(frame)
    per_clip["fabric"] = per_clip["clip_id"].map(clip_fabric)

    fabrics = compare_with_table2(per_clip)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "fabrics.csv"
    atomic_write_text(path, fabrics.to_csv(index=False, float_format="%.6g"))

    known = fabrics.dropna(subset=["table2_class"]) if "table2_class" in fabrics else fabrics.iloc[:0]
    match_rows = []
    for i, score in enumerate(("exact", "p_match", "k_match", "class_dist")):
        if known.empty:
            break
        est = metrics.bootstrap_mean(known[score], known["fabric"], resamples=resamples, confidence=confidence,
                                     rng=np.random.default_rng([seed, stream_id(score)]))
        match_rows.append({"score": score, "fabrics": len(known), **est.as_dict("value")})
    match = pd.DataFrame(match_rows, columns=["score", "fabrics", "value", "value_lo", "value_hi"])
    atomic_write_text(out_dir / "match.csv", match.to_csv(index=False, float_format="%.6g"))

    # Per clip, through the real-video table: predicted bending vs measured stiffness/density.
    videos = real.per_video(frame).merge(per_clip[["clip_id", "fabric"]], left_on="video", right_on="clip_id")
    values = {f: truth(f) for f in videos["fabric"].unique()}
    joined = videos.assign(label=videos["fabric"], stiffness=videos["fabric"].map(lambda f: values[f]["stiffness"]),
                           density=videos["fabric"].map(lambda f: values[f]["density"]))
    corr = real.table4(joined, resamples=resamples, confidence=confidence, seed=seed)
    if not known.empty:  # predicted coefficients against the paper's estimated ratios, per fabric
        for coef in ("p", "k"):
            row = {"group": "fabrics (Table 2)", "videos": len(known), "score": f"predicted {coef} vs Table 2 {coef}~"}
            for method in ("pearson", "spearman"):
                est = metrics.bootstrap_correlation(np.log(known[f"pred_{coef}"]), np.log(known[f"table2_{coef}_est"]),
                                                    method=method, resamples=resamples, confidence=confidence,
                                                    rng=np.random.default_rng([seed, stream_id(coef + method)]))
                row.update(est.as_dict(f"stiffness_{method}"))
            corr = pd.concat([corr, pd.DataFrame([row])], ignore_index=True)
    corr.insert(0, "model", str(train_dir))
    atomic_write_text(out_dir / "correlations.csv", corr.to_csv(index=False, float_format="%.6g"))

    lines = [f"# Measured fabrics (model `{train_dir}`, clips `{clips_dir}`)", "",
             "| Fabric | Clips | Predicted (p, k) | Table 2 (p, k) | Exact | Grid steps |", "|---|---|---|---|---|---|"]
    for _, r in fabrics.iterrows():
        t2 = f"({r['table2_p']:g}, {r['table2_k']:g})" if pd.notna(r.get("table2_p", np.nan)) else "not in Table 2"
        exact = "yes" if r.get("exact") == 1 else ("no" if pd.notna(r.get("exact", np.nan)) else "")
        dist = f"{r['class_dist']:g}" if pd.notna(r.get("class_dist", np.nan)) else ""
        lines.append(f"| {r['fabric']} | {r['clips']} | ({r['pred_p']:g}, {r['pred_k']:g}) | {t2} | {exact} | {dist} |")
    lines += ["", "| Score | Fabrics | Value [95% interval over fabrics] |", "|---|---|---|"]
    lines += [f"| {r.score} | {r.fabrics} | {metrics.Estimate(r.value, r.value_lo, r.value_hi).fmt(1.0, 2)} |"
              for r in match.itertuples()]
    lines += ["", "Correlations: see correlations.csv (the p/k rows hold log-ratio correlations in the "
              "stiffness columns).", ""]
    atomic_write_text(out_dir / "measured.md", "\n".join(lines))
    return path
