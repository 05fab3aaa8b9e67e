"""How much of a setting's lattice target (learn.geometry) is the same for every material.

    python scripts/lattice_variance.py RUN [--setting arm-uniform1] [--out FILE.json]

Reads the simulated clips of a run (no renders needed), standardises their 8 x 8 lattices exactly as training
does (``learn.geometry.standardise``), splits the clips by sequence (odd sequences held out) and reports the
held-out mean squared error, in the target's units, of predictors that know less or more than the material:
the constant (the median shape), the mean shape at each frame index, for arm clips the mean shape at each
forearm pose (5-degree bins while it sweeps, then frames since the sweep ended) and that pose with the
forearm's speed, and the mean shape of each class at each frame index. A regressor whose training error sits
near a predictor's error has learnt about as much as that predictor knows.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import clothgap.config  # noqa: E402,F401  (registers the study config that Run.open reads)
from clothgap.runs import Run, read_meta  # noqa: E402
from learn.geometry import clip_lattices, standardise  # noqa: E402


def _group_means(targets: np.ndarray, keys: np.ndarray, train: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Each (clip, frame)'s prediction: the mean target of the training (clip, frame)s with its key."""
    pred = fallback.copy()
    for key in np.unique(keys):
        here = keys == key
        seen = here & train[:, None]
        if seen.any():
            pred[here] = targets[seen].mean(0)
    return pred


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--setting", default="arm-uniform1")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    run = Run.open(args.run)
    sim_dir = run.sim_dir(args.setting)
    ids = run.done_clips(sim_dir)
    if not ids:
        raise SystemExit(f"{sim_dir}: no finished clip")
    lattices = clip_lattices(run, args.setting, ids, progress=False)
    meta = [read_meta(sim_dir / cid) for cid in ids]
    frames = {len(lattices[c]) for c in ids}
    if len(frames) != 1:
        raise SystemExit(f"clips of {args.setting} have different frame counts: {sorted(frames)}")
    t = frames.pop()
    rows = np.concatenate([lattices[c].reshape(t, -1) for c in ids])
    targets, spread, _far = standardise(rows, {c: slice(i * t, (i + 1) * t) for i, c in enumerate(ids)})
    targets = targets.reshape(len(ids), t, -1)
    held_out = np.array([m["sequence"] % 2 == 1 for m in meta])
    train = ~held_out

    def error(pred: np.ndarray) -> float:
        return round(float(((targets[held_out] - pred[held_out]) ** 2).mean()), 4)

    zero = np.zeros_like(targets)
    frame = np.broadcast_to(np.arange(t), (len(ids), t))
    by_frame = _group_means(targets, frame, train, zero)
    classes = np.array([m["class_index"] for m in meta])
    result = {"run": str(args.run), "setting": args.setting, "clips": len(ids), "frames": t,
              "held_out_clips": int(held_out.sum()), "spread_m": round(spread, 5),
              "mse": {"constant": error(zero), "frame": error(by_frame)}}
    if meta[0]["motion"] == "arm":
        params = [m["motion_params"] for m in meta]
        angle = np.array([p["forearm_angle_deg_per_frame"] for p in params])
        sweep = np.array([p["arm_sweep_deg"] for p in params])[:, None]
        since = np.cumsum(angle >= sweep - 1e-6, axis=1)          # frames since the sweep ended, 0 while it sweeps
        pose = np.where(since > 0, 1000 + np.minimum(since, 30), np.round(angle / 5).astype(int))
        by_pose = _group_means(targets, pose, train, by_frame)
        speed = np.array([p["arm_speed_deg_s"] for p in params])
        quartile = np.digitize(speed, np.quantile(speed[train], [0.25, 0.5, 0.75]))
        result["mse"]["forearm_pose"] = error(by_pose)
        result["mse"]["forearm_pose_and_speed"] = error(_group_means(targets, pose * 10 + quartile[:, None], train,
                                                                     by_pose))
    result["mse"]["class_and_frame"] = error(_group_means(targets, classes[:, None] * 1000 + frame, train, by_frame))
    print(json.dumps(result, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"command": "python " + " ".join(sys.argv), **result}, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
