"""Where a training step's time goes: the real step under a few layouts, and a kernel profile of the first.

    python benchmarks/train_profile.py RUN [--setting wind-uniform1] [--variant paper] [--recipe baseline]
                                       [--model lrcn] [--layouts eager,pad8,graphs] [--warmup 20] [--steps 150]
                                       [--profile-steps 20] [--out FILE]

Runs ``learn.train.run_epoch`` on a run's own training windows (frames resident on the device, cut by
``learn.windows.WindowSet`` as training does, the recipe's model, optimiser and bf16) for ``--steps`` steps per
layout, one after another in one process on the same batches, each from the same starting weights:

- ``eager``: as the recipe trains (the baseline of every ratio);
- ``pad8``: conv1's input channels zero-padded to a multiple of 8 (``PaddedConv``), the same sums;
- ``graphs``: CUDA graphs (``train.compile=true``, ``train.compile_mode=reduce-overhead``);
- ``graphs-pad8``: both.

Then ``--profile-steps`` steps of the first layout under ``torch.profiler``: the GPU's busy time against the
wall time (how much of a step the host leaves the GPU idle) and the kernels ranked by GPU time. Windows/s and
the ratio to ``eager`` of each layout; the issue's goal is 8,000 ten-frame windows/s (80,000 frames/s).
Writes benchmarks/results/train_profile-<device>-<setting>.json with the command.
"""

from __future__ import annotations

import itertools
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, run_arguments, torch_device, write_result  # noqa: E402  (benchmarks/common.py)
from clothgap.runs import Run  # noqa: E402
from eval.ablation import recipe_config  # noqa: E402
from learn.models import model_args  # noqa: E402
from learn.train import (build_training_model, forward_net, make_optimizer, resolve_device, run_epoch,  # noqa: E402
                         window_sets)

LAYOUTS = ("eager", "pad8", "graphs", "graphs-pad8")


class PaddedConv(nn.Module):
    """A convolution whose input channels (conv1's 3, or 6 with frame differences) and weights are padded with
    zeros to a multiple of ``multiple``: the same sums in a layout tensor cores prefer. The ``pad8`` layouts put it
    in place of conv1; measured and not kept in training (docs/learning.md, sixteenth session)."""

    def __init__(self, conv: nn.Conv2d, multiple: int = 8):
        super().__init__()
        self.conv, self.pad = conv, -conv.in_channels % multiple

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        layout = torch.channels_last if x.is_contiguous(memory_format=torch.channels_last) else torch.contiguous_format
        x = F.pad(x, (0, 0, 0, 0, 0, self.pad)).contiguous(memory_format=layout)
        weight = F.pad(self.conv.weight, (0, 0, 0, 0, 0, self.pad))
        return F.conv2d(x, weight, self.conv.bias, self.conv.stride, self.conv.padding)


def _kernel_table(prof, steps: int, top: int = 25) -> tuple[list[dict], float]:
    """The kernels (GPU time per step, ms, and calls per step), most expensive first, and their total.

    Only the device's own events: an operator's entry (``aten::...``) carries its kernels' time too, and
    counting both would count the GPU's time twice."""
    from torch.autograd import DeviceType

    rows = []
    for evt in prof.key_averages():
        if evt.device_type == DeviceType.CPU:
            continue
        gpu_us = evt.self_device_time_total
        if gpu_us > 0:
            rows.append({"name": evt.key[:120], "ms_per_step": round(gpu_us / 1000 / steps, 4),
                         "calls_per_step": round(evt.count / steps, 1)})
    rows.sort(key=lambda r: -r["ms_per_step"])
    return rows[:top], round(sum(r["ms_per_step"] for r in rows), 3)


def main(argv: list[str] | None = None) -> dict:
    ap = run_arguments(__doc__, recipe="baseline")
    ap.add_argument("--layouts", default="eager,pad8,graphs",
                    help=f"comma-separated, the first is the baseline and the one profiled ({', '.join(LAYOUTS)})")
    ap.add_argument("--warmup", type=int, default=20, help="untimed steps first (cuDNN and compile set-up)")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--profile-steps", type=int, default=20, help="0: no kernel profile")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    layouts = args.layouts.split(",")
    unknown = [x for x in layouts if x not in LAYOUTS]
    if unknown:
        raise SystemExit(f"unknown layouts {', '.join(unknown)}; known: {', '.join(LAYOUTS)}")
    run = Run.open(args.run)
    cfg = recipe_config(run.config, args.recipe)
    device = resolve_device(cfg.device)
    train_set, _val = window_sets(run, args.setting, args.variant, cfg, device, progress=False)
    needed = (args.warmup + max(args.steps, args.profile_steps)) * cfg.batch_size
    if len(train_set) < needed:
        raise SystemExit(f"{len(train_set)} training windows, fewer than (warmup + steps) x batch = {needed}")
    amp = cfg.amp and device.type == "cuda"
    order = train_set.order(0, 0)

    def build(layout: str):
        # The layouts say the compile mode themselves: a preset that trains under graphs is profiled eager too.
        lcfg = replace(cfg, compile=layout.startswith("graphs"), compile_mode="reduce-overhead")
        model = build_training_model({"model": args.model, "model_args": model_args(cfg), "torch_seed": 0,
                                      "cnn_init": "random"}, device)
        if layout.endswith("pad8"):
            model.cnn.features[0] = PaddedConv(model.cnn.features[0])
        net, optimizer = forward_net(model, lcfg, device), make_optimizer(model, lcfg, device)
        batches = iter(train_set.batches(cfg.batch_size, order=order, drop_last=True))

        def steps(n: int) -> None:     # run_epoch reads its sums back once at the end: every step has finished
            run_epoch(net, model, itertools.islice(batches, n), device, optimizer, amp,
                      geometry_weight=cfg.geometry_weight, label_smoothing=cfg.label_smoothing,
                      truth_weight=cfg.reader_truth)
        return steps

    frames_per_window = cfg.clip_len
    timings: dict[str, dict] = {}
    for layout in layouts:
        steps = build(layout)
        t0 = time.perf_counter()
        steps(args.warmup)
        warm = time.perf_counter() - t0
        started = time.perf_counter()
        steps(args.steps)
        seconds = time.perf_counter() - started
        wps = args.steps * cfg.batch_size / seconds
        timings[layout] = {"warmup_s": round(warm, 2), "step_ms": round(1000 * seconds / args.steps, 3),
                           "windows_per_s": round(wps, 1), "frames_per_s": round(wps * frames_per_window),
                           "ratio": round(wps / timings[layouts[0]]["windows_per_s"], 3) if timings else 1.0}
        print(f"{layout}: {timings[layout]['step_ms']} ms a step, {timings[layout]['frames_per_s']} frames/s, "
              f"{timings[layout]['ratio']}x", flush=True)

    profile = None
    if args.profile_steps and device.type == "cuda":
        from torch.profiler import ProfilerActivity, profile as torch_profile

        steps = build(layouts[0])
        steps(args.warmup)
        torch.cuda.synchronize()
        with torch_profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            t0 = time.perf_counter()
            steps(args.profile_steps)
            torch.cuda.synchronize()
            wall = time.perf_counter() - t0
        kernels, busy_ms = _kernel_table(prof, args.profile_steps)
        step_ms = 1000 * wall / args.profile_steps
        profile = {"layout": layouts[0], "steps": args.profile_steps, "step_ms_under_profiler": round(step_ms, 3),
                   "gpu_busy_ms_per_step": busy_ms, "gpu_busy_share": round(busy_ms / step_ms, 3),
                   "kernels": kernels}
        print(f"profile: {step_ms:.2f} ms a step, kernels {busy_ms:.2f} ms ({busy_ms / step_ms:.0%} busy)")
        for row in kernels[:12]:
            print(f"  {row['ms_per_step']:8.3f} ms  x{row['calls_per_step']:<6} {row['name']}")

    result = {**torch_device(device), "run": str(args.run), "setting": args.setting, "variant": args.variant,
              "recipe": args.recipe, "model": args.model, "batch_size": cfg.batch_size, "clip_len": cfg.clip_len,
              "image_size": cfg.image_size, "frames_on_device": train_set.resident, "warmup": args.warmup,
              "steps": args.steps, "layouts": timings, "profile": profile}
    out = args.out or RESULTS / f"train_profile-{device.type}-{args.setting}.json"
    write_result("train_profile.py", argv, result, out)
    return result


if __name__ == "__main__":
    main()
