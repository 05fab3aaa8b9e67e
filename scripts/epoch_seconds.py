"""Seconds an epoch of two recipes' models in one run, from their ``metrics.csv``: the median over a range of
epochs of each model, each side's median over its models, and their ratio (README speed row 9: the preset's lrcn
eager against CUDA graphs, every epoch but the first, which compiles).

    python3 scripts/epoch_seconds.py RUN --a "compile=false+epochs=8*" --b "epochs=8*" --epochs 1-7 \\
        --models-per-gpu 2 --out epochs.json

``--epochs`` are values of metrics.csv's ``epoch`` column, which counts from 0. ``--a`` and ``--b`` are glob patterns of recipe folders under ``RUN/ablation``; a model folder counts when it
has ``DONE`` (``--expect N``: each side must have N). Both sides must have trained on the same data. The ratio is a's seconds over b's (how many times faster b is). Frames a second per GPU are the
training windows' frames an epoch (``config.json``: ``train_subsequences`` x ``clip_len``) times the models
sharing a GPU, over the side's median epoch: validation's frames are not counted, its time is.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.files import print_json, script_command  # noqa: E402


def epoch_range(text: str) -> tuple[int, int]:
    first, sep, last = text.partition("-")
    try:
        lo, hi = int(first), int(last if sep else first)
    except ValueError:
        raise SystemExit(f"--epochs {text!r}: expected FIRST-LAST, e.g. 1-7") from None
    if not 0 <= lo <= hi:
        raise SystemExit(f"--epochs {text!r}: expected 0 <= FIRST <= LAST")
    return lo, hi


def model_row(folder: Path, epochs: tuple[int, int]) -> dict:
    curves = pd.read_csv(folder / "metrics.csv")
    config = json.loads((folder / "config.json").read_text())
    lo, hi = epochs
    picked = curves[(curves["epoch"] >= lo) & (curves["epoch"] <= hi)]["seconds"].tolist()
    if len(picked) < hi - lo + 1:
        raise SystemExit(f"{folder}: metrics.csv has {len(picked)} of epochs {lo}-{hi}")
    best = curves["val_acc"].max()
    return {"epochs": len(curves), "first_epoch_s": round(float(curves["seconds"].iloc[0]), 2),
            "median_epoch_s": round(statistics.median(picked), 3),
            "frames_an_epoch": int(config["train_subsequences"]) * int(config["train"]["clip_len"]),
            "best_val_acc": None if pd.isna(best) else round(float(best), 6)}


def side(run: Path, pattern: str, epochs: tuple[int, int], per_gpu: int, expect: int | None = None) -> dict:
    folders = sorted(p.parent for p in run.glob(f"ablation/{pattern}/*/*/*/s*/DONE"))
    if not folders:
        raise SystemExit(f"no finished model under {run}/ablation/{pattern}")
    if expect is not None and len(folders) != expect:
        raise SystemExit(f"{pattern}: {len(folders)} finished models, expected {expect}")
    models = {str(f.relative_to(run / "ablation")): model_row(f, epochs) for f in folders}
    median = statistics.median(m["median_epoch_s"] for m in models.values())
    frames = {m["frames_an_epoch"] for m in models.values()}
    if len(frames) != 1:
        raise SystemExit(f"{pattern}: the models trained on different data ({sorted(frames)} frames an epoch)")
    frames_an_epoch = frames.pop()
    return {"models": models, "median_epoch_s": median, "frames_an_epoch": frames_an_epoch,
            "frames_per_s_per_gpu": round(per_gpu * frames_an_epoch / median)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--a", required=True, help="the baseline's recipe folders (a glob under RUN/ablation)")
    ap.add_argument("--b", required=True, help="the compared recipe's folders")
    ap.add_argument("--epochs", type=epoch_range, default=(1, 7),
                    help="FIRST-LAST of metrics.csv's epoch column, which counts from 0 (default 1-7)")
    ap.add_argument("--models-per-gpu", type=int, default=2)
    ap.add_argument("--expect", type=int, help="finished models each side must have (default: any number)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    a = side(args.run, args.a, args.epochs, args.models_per_gpu, args.expect)
    b = side(args.run, args.b, args.epochs, args.models_per_gpu, args.expect)
    if a["frames_an_epoch"] != b["frames_an_epoch"]:
        raise SystemExit(f"--a and --b trained on different data ({a['frames_an_epoch']} and "
                         f"{b['frames_an_epoch']} frames an epoch): their epochs are not comparable")
    shared = set(a["models"]) & set(b["models"])
    if shared:
        raise SystemExit(f"--a and --b match the same models: {sorted(shared)}")
    result = {"command": script_command(__file__, argv),
              "epochs": list(args.epochs), "models_per_gpu": args.models_per_gpu, "a": a, "b": b,
              "ratio_a_over_b": round(a["median_epoch_s"] / b["median_epoch_s"], 3)}
    print_json(result, args.out)


if __name__ == "__main__":
    main()
