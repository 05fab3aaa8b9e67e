"""What a model costs when it reads a shared regressor's shapes instead of training its own CNN.

    python benchmarks/shared_regressor.py RUN [--setting wind-uniform1] [--variant paper] [--model base3]
                                          [--regressor lrcn] [--seed 0] [--epochs 80] [--out FILE]

On a run whose ``--regressor`` model is trained (``RUN/train/SETTING/VARIANT/REGRESSOR/sSEED``), in one
process, on the run's own training windows as training cuts them (``learn.train.window_sets``, the run's train
settings, its device, bf16 and compile settings): one training epoch of ``--model`` with its own CNN
(``learn.train.run_epoch`` on the frames), then the shared regressor's one pass over the training and
validation windows (``learn.shapes.ShapeSet``), then one training epoch of the same model's readers on those
shapes (``train.shared_regressor``). Each epoch runs twice and the second is timed (the first holds cuDNN's
and the allocator's set-up). Reports windows/s of both epochs, their ratio, and the ratio for a whole training
of ``--epochs`` epochs with the shapes' pass counted once. Validation is not timed in either. Writes
benchmarks/results/shared_regressor-<device>-<setting>.json with the command.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, run_arguments, torch_device, write_result  # noqa: E402  (benchmarks/common.py)
from clothgap.runs import Run  # noqa: E402
from learn.models import ShapeReader, model_args  # noqa: E402
from learn.train import (build_training_model, forward_net, make_optimizer, resolve_device, run_epoch,  # noqa: E402
                         shape_sets, window_sets)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main(argv: list[str] | None = None) -> dict:
    ap = run_arguments(__doc__, model="base3", model_help="the model whose two ways of training are timed")
    ap.add_argument("--regressor", default="lrcn", help="the trained model whose CNN and lattice head it reads")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--epochs", type=int, default=80, help="a whole training's epochs, for the per-model ratio")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    run = Run.open(args.run)
    if args.model == args.regressor:
        raise SystemExit("--model must differ from --regressor: the regressor trains its own CNN either way")
    source = run.train_dir(args.setting, args.variant, args.regressor, args.seed) / "checkpoint.pt"
    if not source.is_file():
        raise SystemExit(f"{source} does not exist: train {args.regressor} of seed {args.seed} first")
    cfg = dataclasses.replace(run.config.train, shared_regressor=args.regressor)
    if not cfg.bottleneck:
        raise SystemExit("the run's recipe has no bottleneck (train.bottleneck=false): nothing reads a shape alone")
    device = resolve_device(cfg.device)
    amp = cfg.amp and device.type == "cuda"
    train_set, val_set = window_sets(run, args.setting, args.variant, cfg, device, progress=False)
    order = train_set.order(0, 0)
    windows = len(order) - len(order) % cfg.batch_size       # an epoch's full batches (drop_last, as training)
    if not windows:
        raise SystemExit(f"{len(order)} training windows, fewer than one batch of {cfg.batch_size}")
    common = dict(geometry_weight=cfg.geometry_weight, label_smoothing=cfg.label_smoothing,
                  truth_weight=cfg.reader_truth)

    def epoch_seconds(net, model, batches_of) -> float:
        optimizer = make_optimizer(model, cfg, device)
        run_epoch(net, model, batches_of(), device, optimizer, amp, **common)           # set-up
        _sync(device)
        started = time.perf_counter()
        run_epoch(net, model, batches_of(), device, optimizer, amp, **common)           # reads its sums back
        return time.perf_counter() - started

    resolved = {"model": args.model, "model_args": model_args(cfg), "torch_seed": 0, "cnn_init": "random"}
    own = build_training_model(resolved, device)
    own_s = epoch_seconds(forward_net(own, cfg, device), own,
                          lambda: train_set.batches(cfg.batch_size, order=order, drop_last=True))
    del own

    shared = {**resolved, "cnn_init": str(source), "train": {"shared_regressor": args.regressor}}
    _sync(device)
    started = time.perf_counter()
    shapes = shape_sets(shared, train_set, val_set, cfg, device)        # what a reader's training does first
    _sync(device)
    shape_s = time.perf_counter() - started
    reader_model = build_training_model(shared, device)
    reader_s = epoch_seconds(forward_net(ShapeReader(reader_model), cfg, device, reads_shapes=True), reader_model,
                             lambda: shapes[0].batches(cfg.batch_size, order=order, drop_last=True))

    result = {**torch_device(device), "run": str(args.run), "setting": args.setting, "variant": args.variant,
              "model": args.model, "regressor": args.regressor, "seed": args.seed, "image_size": cfg.image_size,
              "clip_len": cfg.clip_len, "batch_size": cfg.batch_size, "train_windows": len(train_set),
              "windows_an_epoch": windows,
              "val_windows": len(val_set), "frames_on_device": train_set.resident,
              "own_cnn": {"epoch_s": round(own_s, 4), "windows_per_s": round(windows / own_s, 1)},
              "shapes_pass_s": round(shape_s, 4),
              "reader_on_shapes": {"epoch_s": round(reader_s, 4), "windows_per_s": round(windows / reader_s, 1)},
              "epoch_speedup": round(own_s / reader_s, 2),
              "epochs": args.epochs,
              "training_speedup": round(args.epochs * own_s / (shape_s + args.epochs * reader_s), 2)}
    out = args.out or RESULTS / f"shared_regressor-{device.type}-{args.setting}.json"
    write_result("shared_regressor.py", argv, result, out)
    print(f"{args.model}: an epoch with its own CNN {own_s:.3f} s, on {args.regressor}'s shapes {reader_s:.3f} s "
          f"({result['epoch_speedup']}x); the shapes' pass {shape_s:.3f} s; {args.epochs} epochs "
          f"{result['training_speedup']}x")
    return result


if __name__ == "__main__":
    main()
