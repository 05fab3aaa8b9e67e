"""Training throughput of a learn model: an eager fp32 baseline against bf16 + torch.compile + channels_last.

Both loops run in the same process on the same device and the same batches
(random uint8 clips made once on the host and copied over every step, as a
DataLoader would), so the ratio is a fair measure of what the fast path buys.
Data loading itself is not timed. Writes a JSON under benchmarks/results/ with
the command line, the device, the settings and clips/s of each loop.

    python benchmarks/train_throughput.py                      # the GPU, paper-scale model
    python benchmarks/train_throughput.py --device cpu --image-size 64 --width 16 --fc6 128 \\
        --hidden 64 --batch-size 4 --steps 3 --warmup 1         # a quick CPU check

On CPU, torch.compile is skipped unless --cpu-compile is given (it needs a C++
toolchain and minutes of compiling), and bf16 autocast runs as asked.
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import torch

from learn.dataset import to_input
from learn.models import build_model
from learn.registry import MODEL_NAMES
from learn.train import resolve_device

RESULTS = Path(__file__).resolve().parent / "results"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:N")
    p.add_argument("--model", default="lrcn", choices=MODEL_NAMES)
    p.add_argument("--image-size", type=int, default=112)
    p.add_argument("--clip-len", type=int, default=10)
    p.add_argument("--batch-size", type=int, default=64, help="clips per step")
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--fc6", type=int, default=512)
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--steps", type=int, default=30, help="timed training steps per loop")
    p.add_argument("--warmup", type=int, default=10, help="untimed steps first (compilation happens here)")
    p.add_argument("--cpu-compile", action="store_true", help="also torch.compile on CPU")
    p.add_argument("--out", type=Path, help="JSON path (default: benchmarks/results/train_throughput-<device>-<time>.json)")
    return p.parse_args(argv)


def time_loop(args: argparse.Namespace, device: torch.device, batches: list[tuple[torch.Tensor, torch.Tensor]],
              amp: bool, compile_: bool, channels_last: bool) -> dict:
    """Train ``args.model`` for warmup + steps steps; clips/s over the timed steps."""
    torch.manual_seed(0)
    model = build_model(args.model, image_size=args.image_size, width=args.width, fc6=args.fc6,
                        hidden=args.hidden).to(device)
    if channels_last:
        model.cnn.to(memory_format=torch.channels_last)
        model.cnn.register_forward_pre_hook(lambda _m, inp: (inp[0].contiguous(memory_format=torch.channels_last),))
    net = torch.compile(model) if compile_ else model
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    model.train()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)

    def step(i: int) -> None:
        frames, labels = batches[i % len(batches)]
        x, y = to_input(frames, device), labels.to(device, non_blocking=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            out = net(x)
        loss = model.loss(out, y)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    started = time.perf_counter()
    for i in range(args.warmup):
        step(i)
    sync()
    warm = time.perf_counter()
    for i in range(args.steps):
        step(i)
    sync()
    seconds = time.perf_counter() - warm
    result = {"amp_bf16": amp, "compile": compile_, "channels_last": channels_last,
              "warmup_seconds": round(warm - started, 3), "timed_seconds": round(seconds, 4),
              "step_ms": round(1000 * seconds / args.steps, 3),
              "clips_per_s": round(args.batch_size * args.steps / seconds, 2)}
    if device.type == "cuda":
        result["peak_memory_gib"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 3)
    return result


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "cpu"


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    device = resolve_device(args.device)
    gen = torch.Generator().manual_seed(0)
    shape = (args.batch_size, args.clip_len, 3, args.image_size, args.image_size)
    batches = [(torch.randint(0, 256, shape, dtype=torch.uint8, generator=gen),
                torch.randint(0, 54, (args.batch_size,), generator=gen)) for _ in range(4)]
    if device.type == "cuda":
        batches = [(f.pin_memory(), y.pin_memory()) for f, y in batches]
        torch.backends.cudnn.benchmark = True
    compile_fast = device.type == "cuda" or args.cpu_compile
    loops = {"eager_fp32": time_loop(args, device, batches, amp=False, compile_=False, channels_last=False),
             "bf16_compile_channels_last": time_loop(args, device, batches, amp=True, compile_=compile_fast,
                                                     channels_last=True)}
    report = {
        "command": shlex.join([Path(sys.executable).name, *sys.argv]) if argv is None else shlex.join(["train_throughput", *argv]),
        "when": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else _cpu_name(),
        "torch": torch.__version__, "threads": torch.get_num_threads(),
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "loops": loops,
        "speedup": round(loops["bf16_compile_channels_last"]["clips_per_s"] / loops["eager_fp32"]["clips_per_s"], 3),
    }
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    out = args.out or RESULTS / f"train_throughput-{device.type}-{stamp}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    main()
