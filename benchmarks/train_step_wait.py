"""What a wait for the GPU in every training step costs: the real training step with and without one.

    python benchmarks/train_step_wait.py RUN [--setting wind-uniform1] [--variant paper] [--recipe best]
                                         [--model lrcn] [--warmup 20] [--steps 200] [--out FILE]

Runs ``learn.train.run_epoch`` on a run's own training windows (frames resident on the device, cut by
``learn.windows.WindowSet`` as training does, the recipe's model, optimiser, bf16 and compile settings) for
``--steps`` steps twice in one process: as training runs them now, and with a blocking host-to-device copy
before each step, which is what ``run_epoch`` did until the step's clip count stopped being made as a tensor
from a number (the host then waits for the GPU to finish a step before it launches the next). Windows/s of
both and their ratio, the same batches in the same order. On a CPU the copy costs nothing; the figure is a
GPU's. Writes benchmarks/results/train_step_wait-<device>-<setting>.json with the command.
"""

from __future__ import annotations

import itertools
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, run_arguments, torch_device, write_result  # noqa: E402  (benchmarks/common.py)
from clothgap.runs import Run  # noqa: E402
from eval.ablation import recipe_config  # noqa: E402
from learn.models import model_args  # noqa: E402
from learn.train import (build_training_model, forward_net, make_optimizer, resolve_device, run_epoch,  # noqa: E402
                         window_sets)


def _with_wait(batches, device: torch.device):
    for batch in batches:
        torch.tensor(float(len(batch[1])), device=device)      # blocking: the host waits for the stream
        yield batch


def main(argv: list[str] | None = None) -> dict:
    ap = run_arguments(__doc__, recipe="best")
    ap.add_argument("--warmup", type=int, default=20, help="untimed steps first (cuDNN and compile set-up)")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    run = Run.open(args.run)
    cfg = recipe_config(run.config, args.recipe)
    device = resolve_device(cfg.device)
    train_set, _val = window_sets(run, args.setting, args.variant, cfg, device, progress=False)
    needed = (args.warmup + args.steps) * cfg.batch_size
    if len(train_set) < needed:
        raise SystemExit(f"{len(train_set)} training windows, fewer than (warmup + steps) x batch = {needed}")
    amp = cfg.amp and device.type == "cuda"
    order = train_set.order(0, 0)

    def timed(wait: bool) -> dict:
        model = build_training_model({"model": args.model, "model_args": model_args(cfg), "torch_seed": 0,
                                      "cnn_init": "random"}, device)
        net, optimizer = forward_net(model, cfg, device), make_optimizer(model, cfg, device)
        batches = iter(train_set.batches(cfg.batch_size, order=order, drop_last=True))
        if wait:
            batches = _with_wait(batches, device)

        def steps(n: int) -> None:     # run_epoch reads its sums back once at the end: every step has finished
            run_epoch(net, model, itertools.islice(batches, n), device, optimizer, amp,
                      geometry_weight=cfg.geometry_weight, label_smoothing=cfg.label_smoothing,
                      truth_weight=cfg.reader_truth)

        steps(args.warmup)
        started = time.perf_counter()
        steps(args.steps)
        seconds = time.perf_counter() - started
        return {"seconds": round(seconds, 4), "step_ms": round(1000 * seconds / args.steps, 3),
                "windows_per_s": round(args.steps * cfg.batch_size / seconds, 1)}

    with_wait = timed(wait=True)
    without = timed(wait=False)
    result = {**torch_device(device), "run": str(args.run), "setting": args.setting, "variant": args.variant,
              "recipe": args.recipe, "model": args.model, "batch_size": cfg.batch_size, "clip_len": cfg.clip_len,
              "compile": cfg.compile and device.type == "cuda", "compile_mode": cfg.compile_mode,
              "frames_on_device": train_set.resident, "warmup": args.warmup, "steps": args.steps,
              "with_a_wait_each_step": with_wait, "as_training_runs": without,
              "speedup": round(without["windows_per_s"] / with_wait["windows_per_s"], 3)}
    out = args.out or RESULTS / f"train_step_wait-{device.type}-{args.setting}.json"
    write_result("train_step_wait.py", argv, result, out)
    print(f"{result['as_training_runs']['windows_per_s']} windows/s as training runs, "
          f"{result['with_a_wait_each_step']['windows_per_s']} with a wait each step: {result['speedup']}x")
    return result


if __name__ == "__main__":
    main()
