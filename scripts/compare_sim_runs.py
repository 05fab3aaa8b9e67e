"""Two runs of the same seeds and settings simulated by two versions of the solver: a systematic change, or rounding?

A change to the solver that should only move rounding (a dot product summed in another order, kernels fused) still
moves chaotic clips (a cloth on a turning arm) by millimetres to centimetres. What matters is whether the clips'
distribution moved. For each clip id finished in both runs this pairs, new minus old:

- the CG iterations a step (``health.cg_iterations_mean``);
- the cloth's mean height, its vertical and horizontal extent, and its mean speed per frame, averaged over frames;

each with a 95 % interval from resampling clips (``eval.metrics.bootstrap_mean``), beside the spread of the old run's clips (so a shift reads against
how much clips differ anyway). It also gives the last frame's RMS vertex distance between the two versions of one
clip against that between two sequences of one class in the old run: rounding chaos keeps the first below the
second.

    python scripts/compare_sim_runs.py OLD_RUN NEW_RUN --setting arm-uniform1 [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.runs import is_done  # noqa: E402
from eval.metrics import bootstrap_mean  # noqa: E402
from sim.clip import SimClip  # noqa: E402

SHAPES = ("mean_height_m", "vertical_extent_m", "horizontal_extent_m", "speed_m_per_frame")


def load_clip(folder: Path) -> tuple[dict, np.ndarray]:
    """A uniform clip's meta and positions, (frames, vertices, 3), read once."""
    clip = SimClip.load(folder)
    if len(set(np.diff(clip.vertex_offsets))) != 1:
        raise SystemExit(f"compare_sim_runs: {folder} changes its mesh between frames (an adaptive clip): "
                         "only uniform settings compare vertex by vertex")
    return clip.meta, clip.positions.reshape(clip.num_frames, -1, 3)


def rms_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean square distance between two frames' vertices (V, 3), metres."""
    return float(np.sqrt(((a - b) ** 2).sum(-1).mean()))


def shape_summary(frames: np.ndarray) -> dict[str, float]:
    z = frames[..., 2]
    xy = frames[..., :2]
    return {"mean_height_m": float(z.mean()),
            "vertical_extent_m": float((z.max(1) - z.min(1)).mean()),
            "horizontal_extent_m": float(np.linalg.norm(xy.max(1) - xy.min(1), axis=-1).mean()),
            "speed_m_per_frame": float(np.linalg.norm(np.diff(frames, axis=0), axis=-1).mean())}


def compare(old_run: Path, new_run: Path, setting: str) -> dict:
    old_dir, new_dir = old_run / "sim" / setting, new_run / "sim" / setting
    ids = sorted(p.name for p in old_dir.iterdir() if is_done(p) and is_done(new_dir / p.name)) \
        if old_dir.is_dir() and new_dir.is_dir() else []
    if len(ids) < 2:
        raise SystemExit(f"compare_sim_runs: {len(ids)} clip(s) of {setting} finished in both {old_run} and "
                         f"{new_run}: nothing to compare")
    differences = {k: [] for k in ("cg_iterations_mean", *SHAPES)}
    old_values = {k: [] for k in SHAPES}
    drift, by_class = [], {}
    for cid in ids:
        (old_meta, old), (new_meta, new) = load_clip(old_dir / cid), load_clip(new_dir / cid)
        if old_meta["class_index"] != new_meta["class_index"]:
            raise SystemExit(f"compare_sim_runs: {cid} is class {old_meta['class_index']} in {old_run} and "
                             f"{new_meta['class_index']} in {new_run}: not runs of the same seeds and settings")
        differences["cg_iterations_mean"].append(new_meta["health"]["cg_iterations_mean"]
                                                 - old_meta["health"]["cg_iterations_mean"])
        s_old, s_new = shape_summary(old), shape_summary(new)
        for k in SHAPES:
            differences[k].append(s_new[k] - s_old[k])
            old_values[k].append(s_old[k])
        drift.append(rms_distance(new[-1], old[-1]))
        by_class.setdefault(old_meta["class_index"], []).append(old[-1])
    between = [rms_distance(a, b) for last in by_class.values() for i, a in enumerate(last) for b in last[i + 1:]]
    def interval(values) -> dict[str, float]:             # one value a clip: resampled clip by clip
        estimate = bootstrap_mean(values, ids)
        return {"mean": estimate.value, "lo": estimate.low, "hi": estimate.high}

    return {
        "old_run": str(old_run), "new_run": str(new_run), "setting": setting, "clips": len(ids),
        "new_minus_old": {k: interval(v) for k, v in differences.items()},
        "old_spread_across_clips": {k: float(np.std(v)) for k, v in old_values.items()},
        "last_frame_rms_m": {
            "same_clip_old_vs_new": {"median": float(np.median(drift)), "mean": float(np.mean(drift)),
                                     "max": float(np.max(drift))},
            "two_sequences_of_one_class_old": {"median": float(np.median(between)) if between else None,
                                               "pairs": len(between)}},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old_run", type=Path)
    ap.add_argument("new_run", type=Path)
    ap.add_argument("--setting", required=True)
    ap.add_argument("--out", type=Path, help="also write the result here, with the command")
    args = ap.parse_args(argv)
    result = compare(args.old_run, args.new_run, args.setting)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        command = "python scripts/compare_sim_runs.py " + " ".join(argv if argv is not None else sys.argv[1:])
        args.out.write_text(json.dumps({"command": command, **result}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
