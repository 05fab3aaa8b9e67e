"""One model trained on N GPUs with torchrun (DDP) against one GPU, on the same clips of a rendered run.

    python benchmarks/train_scaling.py RUN --setting wind-uniform1 --variant paper --model lrcn \
        --recipe best --gpus 2 [--work DIR] [--out DIR]

Each side is its own process tree: the baseline ``python`` on the first GPU, the candidate
``torchrun --standalone --nproc-per-node N`` (``learn.train.train_one`` under an initialised process
group, as ``torchrun -m learn`` trains). The global batch is the recipe's ``batch_size`` on both sides
(``batch_size / N`` per process), so both take the same optimiser steps on the same windows per epoch
and the same final accuracy is expected; ``--per-process-batch`` keeps ``batch_size`` per process instead
(N times the global batch, 1/N of the steps). Writes ``train_scaling-<N>gpu-<model>[-per-process-batch].json``: windows/s
(epochs after the first), the seconds of the epochs and of the whole process (start-up, frames to the
GPU), the time each side took to first reach the validation accuracy both reach, and test top-1 of each
with its interval and their paired difference. A side whose model is finished (``DONE`` under --work)
is not trained again, so a call cut off resumes; its timings then are not one run's (delete its folder).
On a CPU machine ``--gpus 2 --device cpu`` runs two gloo processes: a check of the script, not a figure.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RESULTS = Path(__file__).resolve().parent / "results"


def arguments(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run folder with rendered clips of --setting / --variant")
    ap.add_argument("--setting", required=True)
    ap.add_argument("--variant", required=True)
    ap.add_argument("--model", default="lrcn")
    ap.add_argument("--recipe", default="", help="an eval.ablation recipe (default: the run's train settings)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gpus", type=int, default=2, help="processes of the candidate (one GPU each)")
    ap.add_argument("--per-process-batch", action="store_true",
                    help="batch_size per process (N times the global batch) instead of batch_size / N")
    ap.add_argument("--device", default=None, help="replaces train.device (cpu: a check of the script)")
    ap.add_argument("--work", type=Path, default=None, help="training folders (default RUN/train_scaling)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder for the result JSON")
    ap.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)   # the processes of one side
    return ap.parse_args(argv)


def side_config(run, args, world: int):
    """The recipe's train settings for a side of ``world`` processes."""
    from eval.ablation import recipe_config

    cfg = recipe_config(run.config, args.recipe) if args.recipe else run.config.train
    changes = {}
    if world > 1 and not args.per_process_batch:
        if cfg.batch_size % world:
            raise SystemExit(f"batch_size {cfg.batch_size} does not split over {world} processes")
        changes["batch_size"] = cfg.batch_size // world
    if args.device:
        changes["device"] = args.device
    return dataclasses.replace(cfg, **changes)


def side_root(args, world: int) -> Path:
    return (args.work or args.run / "train_scaling") / f"{args.model}-w{world}"


def child(args) -> None:
    """One process of a side: train the model (under torchrun, this rank's share of each epoch)."""
    import torch

    import clothgap.config  # noqa: F401  (registers the study config that Run.open reads)
    from clothgap.runs import Run
    from learn.train import train_one

    world = int(os.environ.get("WORLD_SIZE", 1))
    if world > 1:
        if torch.cuda.is_available() and args.device != "cpu":
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
            torch.distributed.init_process_group("nccl")
        else:
            torch.distributed.init_process_group("gloo")
    try:
        run = Run.open(args.run)
        train_one(run, args.setting, args.variant, args.model, args.seed, progress=False,
                  config=side_config(run, args, world), root=side_root(args, world))
    finally:
        if torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


def run_side(args, world: int, argv: list[str]) -> float | None:
    """Train one side in its own processes; returns their wall seconds (None when it had finished before)."""
    from clothgap.runs import is_done
    from learn.train import train_folder

    folder = train_folder(None, args.setting, args.variant, args.model, args.seed, side_root(args, world))
    if is_done(folder):
        return None
    me = [str(Path(__file__).resolve()), *argv, "--child", "1"]
    env = dict(os.environ)
    if world == 1:
        cmd = [sys.executable, *me]
        visible = env.get("CUDA_VISIBLE_DEVICES")
        if visible:
            env["CUDA_VISIBLE_DEVICES"] = visible.split(",")[0]
        elif args.device != "cpu":
            env["CUDA_VISIBLE_DEVICES"] = "0"
    else:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(world), *me]
    # NVLink multicast stays off on shared multi-GPU hosts (it can take the host's GPUs out of service)
    env.setdefault("NCCL_NVLS_ENABLE", "0")
    env.setdefault("TORCH_SYMM_MEM_DISABLE_MULTICAST", "1")
    print(f"[train_scaling] {world} process(es): training {folder}", flush=True)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env)
    if done.returncode != 0:
        raise SystemExit(f"the {world}-process side failed (exit {done.returncode})")
    return round(time.perf_counter() - t0, 2)


def side_report(folder: Path, wall: float | None) -> dict:
    from eval.ablation import training_speed

    curves = pd.read_csv(folder / "metrics.csv")
    config = json.loads((folder / "config.json").read_text())
    speed = training_speed(folder)      # windows/s over the epochs after the first, kept epoch, ...
    return {"folder": str(folder), "world_size": config["world_size"], "batch_per_process": config["train"]["batch_size"],
            "process_seconds": wall, "epoch_seconds": speed["train_seconds"],
            "first_epoch_seconds": speed["first_epoch_seconds"], "windows_per_s": speed["windows_per_s"],
            "train_windows": speed["train_windows"], "best_val_acc": round(float(curves["val_acc"].max()), 4),
            "kept_epoch": speed["kept_epoch"],
            "curve": curves[["epoch", "seconds", "val_acc", "train_acc"]].round(4).to_dict(orient="records")}


def seconds_to(curve: list[dict], target: float) -> float | None:
    """Epoch seconds until validation accuracy first reaches ``target``."""
    total = 0.0
    for row in curve:
        total += row["seconds"]
        if row["val_acc"] >= target - 1e-9:
            return round(total, 2)
    return None


def test_scores(run, args, folders: dict[int, Path]) -> dict:
    """Test top-1 of each side with its interval, and the candidate minus the baseline (paired by sequence)."""
    from eval import metrics
    from learn.dataset import build_cache
    from learn.predict import predict_windows
    from learn.split import get_or_make_split, part_windows
    from learn.train import resolve_device

    cfg = side_config(run, args, 1)
    test = part_windows(get_or_make_split(run, args.setting), "test")
    cache = build_cache(run, args.variant, args.setting, cfg.image_size, progress=False)
    device = resolve_device(cfg.device)
    boot = dict(resamples=run.config.eval.bootstrap, confidence=run.config.eval.confidence)
    out, flags = {}, {}
    for world, folder in folders.items():
        frame = predict_windows(folder, cache, test, device)
        truth, pred, groups = frame["class_index"].to_numpy(), frame["pred"].to_numpy(), frame["clip_id"].to_numpy()
        mean = metrics.bootstrap_mean(metrics.correct(truth, pred), groups, rng=np.random.default_rng(world), **boot)
        out[world] = {"top1": round(mean.value, 4), "top1_interval": [round(mean.low, 4), round(mean.high, 4)],
                      "test_windows": len(frame)}
        flags[world] = (metrics.correct(truth, pred), groups)
    if len(flags) == 2:
        (w1, (a, ga)), (wn, (b, gb)) = sorted(flags.items())
        diff = metrics.bootstrap_mean_difference(b, gb, a, ga, rng=np.random.default_rng(0), **boot)
        out["difference"] = {"candidate_minus_baseline": round(diff.value, 4),
                             "interval": [round(diff.low, 4), round(diff.high, 4)]}
    return out


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = arguments(argv)
    if args.child:
        child(args)
        return
    import clothgap.config  # noqa: F401
    from clothgap.runs import Run
    from learn.dataset import build_cache
    from learn.geometry import clip_lattices
    from learn.train import train_folder

    run = Run.open(args.run)
    cfg = side_config(run, args, 1)
    # caches built once here, so that neither side's time includes writing them
    cache = build_cache(run, args.variant, args.setting, cfg.image_size, progress=False)
    if cfg.geometry_weight:
        clip_lattices(run, args.setting, sorted(cache.clips), False)
    del cache
    walls, folders = {}, {}
    for world in (1, args.gpus):
        walls[world] = run_side(args, world, argv)
        folders[world] = train_folder(run, args.setting, args.variant, args.model, args.seed, side_root(args, world))
    sides = {w: side_report(f, walls[w]) for w, f in folders.items()}
    target = min(s["best_val_acc"] for s in sides.values())
    for s in sides.values():
        s["seconds_to_common_val_acc"] = seconds_to(s["curve"], target)
    base, cand = sides[1], sides[args.gpus]
    result = {
        "command": "python benchmarks/train_scaling.py " + " ".join(argv),
        "host": platform.node(), "run": str(args.run), "setting": args.setting, "variant": args.variant,
        "model": args.model, "recipe": args.recipe or "(the run's train settings)", "seed": args.seed,
        "gpus": args.gpus, "global_batch_kept": not args.per_process_batch,
        "common_val_acc": target, "baseline": base, "candidate": cand,
        "speedup": {"windows_per_s": round(cand["windows_per_s"] / base["windows_per_s"], 2),
                    "epoch_seconds": round(base["epoch_seconds"] / cand["epoch_seconds"], 2),
                    "to_common_val_acc": (round(base["seconds_to_common_val_acc"] / cand["seconds_to_common_val_acc"], 2)
                                          if base["seconds_to_common_val_acc"] and cand["seconds_to_common_val_acc"]
                                          else None),
                    "process_seconds": (round(base["process_seconds"] / cand["process_seconds"], 2)
                                        if base["process_seconds"] and cand["process_seconds"] else None)},
        "test": {str(k): v for k, v in test_scores(run, args, folders).items()},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"train_scaling-{args.gpus}gpu-{args.model}{'-per-process-batch' if args.per_process_batch else ''}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["speedup"]), json.dumps(result["test"]), f"-> {path}")


if __name__ == "__main__":
    main()
