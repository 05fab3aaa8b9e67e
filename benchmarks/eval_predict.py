"""The eval's prediction: each test frame read once for every model against once a model.

    python benchmarks/eval_predict.py RUN --models TRAIN_DIR,TRAIN_DIR,... [--setting wind-uniform1]
                                      [--variant paper] [--out FILE]

Predicts every model (training folders with a checkpoint.pt, e.g. ``RUN/train/...`` or ``RUN/ablation/...``) on
the setting's rendered test clips of ``--variant`` twice in one process: ``learn.predict.predict_clips`` a model
(how the eval stage predicted before, each model reading every clip's frames again), and one
``learn.predict.CachedPredictor`` for all of them (how it predicts now). Before either, one untimed pass reads
every clip so both find the files in the page cache, and one untimed prediction sets CUDA up. (``predict_clips``
now reads a model's whole clip list before predicting, where the eval stage once streamed clip by clip: the same
reads.) Checks the two give the same predictions and writes the
seconds of each and their ratio to benchmarks/results/eval_predict-<device>-<setting>.json with the command.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, torch_device, write_result  # noqa: E402  (benchmarks/common.py)
from clothgap.runs import Run, is_done  # noqa: E402
from eval.stage import test_clips  # noqa: E402
from learn.dataset import read_frames  # noqa: E402
from learn.predict import CachedPredictor, load_checkpoint, predict_clips  # noqa: E402
from learn.train import resolve_device  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--models", required=True, help="comma-separated training folders")
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--variant", default="paper")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    run = Run.open(args.run)
    models = [Path(m) for m in args.models.split(",") if m]
    folder = run.render_dir(args.variant, args.setting)
    clips = [folder / c for c in test_clips(run, args.setting) if is_done(folder / c)]
    if not clips or not models:
        raise SystemExit(f"nothing to predict: {len(clips)} rendered test clips in {folder}, {len(models)} models")
    device = resolve_device(args.device)
    size = load_checkpoint(models[0])["model_args"]["image_size"]

    t0 = time.perf_counter()
    for clip in clips:
        read_frames(clip, size)
    warm_read = time.perf_counter() - t0

    def timed(predict) -> tuple[float, list]:
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        frames = [predict(m) for m in models]
        return time.perf_counter() - t0, frames

    predict_clips(models[0], clips[:8], device=str(device))     # CUDA and cuDNN set up before either clock
    per_model_s, per_model = timed(lambda m: predict_clips(m, clips, device=str(device)))
    cached = CachedPredictor(device=str(device))
    cached_s, shared = timed(lambda m: cached(m, clips))
    same_rows = all(a[["clip_id", "start"]].equals(b[["clip_id", "start"]]) for a, b in zip(per_model, shared))
    max_diff = max(float(np.abs(np.stack(a["probs"]) - np.stack(b["probs"])).max())
                   for a, b in zip(per_model, shared))
    result = {**torch_device(device), "run": str(args.run), "setting": args.setting, "variant": args.variant,
              "models": [str(m) for m in models], "test_clips": len(clips), "image_size": size,
              "windows_per_model": len(per_model[0]), "warm_read_s": round(warm_read, 2),
              "predict_clips_per_model_s": round(per_model_s, 2), "cached_predictor_s": round(cached_s, 2),
              "speedup": round(per_model_s / cached_s, 2), "same_rows": same_rows,
              "max_probability_difference": max_diff}
    print(f"{len(models)} models on {len(clips)} clips: {per_model_s:.1f} s a model's own read, {cached_s:.1f} s "
          f"read once ({result['speedup']}x); same rows {same_rows}, largest probability difference {max_diff:.2g}")
    out = args.out or RESULTS / f"eval_predict-{device.type}-{args.setting}.json"
    write_result("eval_predict.py", argv, result, out)
    return result


if __name__ == "__main__":
    main()
