"""A reader's training step (the readers of a shared regressor): the predicted and the true shape read as one batch
against one after another.

    python benchmarks/reader_step.py [--device auto] [--model base2] [--batch-size 16] [--frames 40] [--steps 200]
                                     [--warmup 20] [--out FILE]

Under ``train.shared_regressor`` base1-3 train their readers alone on the regressor's cached shapes, with
``train.reader_truth`` reading the simulation's own lattice as well: two passes through the readers a step.
``ClipClassifier.read_shape`` reads both as one batch (the same sums a clip: tests/test_learn_models.py). This
times the preset's reader (hidden 256, the lattice's 192 numbers, noise 0.2, truth weight 1, AdamW, bf16 on CUDA)
on random shapes held on the device, both ways in one process from the same weights, and writes the ms a step,
windows/s and their ratio to benchmarks/results/reader_step-<device>-<model>.json with the command.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, write_result  # noqa: E402  (benchmarks/common.py)
from learn.models import GEOMETRY_DIM, ShapeReader, build_model  # noqa: E402
from learn.train import resolve_device  # noqa: E402


def read_apart(model, geometry: torch.Tensor, lattice: torch.Tensor) -> dict[str, torch.Tensor]:
    """``read_shape`` as two passes through the readers, the predicted shape and then the true one."""
    out = model.read_lattice(model._noised(geometry.detach().float()))
    out["truth_logits"] = model.read_lattice(model._noised(lattice.float()))["logits"]
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--model", default="base2", choices=("base1", "base2", "base3"))
    ap.add_argument("--batch-size", type=int, default=16)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    amp = device.type == "cuda"
    gen = torch.Generator().manual_seed(0)
    shape = torch.randn(args.batch_size, args.frames, GEOMETRY_DIM, generator=gen).to(device)
    lattice = torch.randn(args.batch_size, args.frames, GEOMETRY_DIM, generator=gen).to(device)
    labels = torch.randint(0, 54, (args.batch_size,), generator=gen).to(device)

    def timed(one_batch: bool) -> dict:
        torch.manual_seed(0)
        model = build_model(args.model, image_size=112, width=64, fc6=512, hidden=256, dropout=0.0, motion=True,
                            geometry_dim=GEOMETRY_DIM, bottleneck=True, bottleneck_noise=0.2).to(device).train()
        reader = ShapeReader(model)
        optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-3,
                                      weight_decay=0.05, fused=device.type == "cuda")

        def step() -> None:
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
                out = reader(shape, lattice) if one_batch else read_apart(model, shape, lattice)
            loss = model.loss(out, labels, truth_weight=1.0)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        for _ in range(args.warmup):
            step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(args.steps):
            step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - start
        return {"step_ms": round(1000 * seconds / args.steps, 3),
                "windows_per_s": round(args.steps * args.batch_size / seconds, 1)}

    apart = timed(one_batch=False)
    together = timed(one_batch=True)
    result = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "torch": torch.__version__, "threads": torch.get_num_threads(), "model": args.model,
              "batch_size": args.batch_size, "frames": args.frames, "warmup": args.warmup, "steps": args.steps,
              "two_passes": apart, "one_batch": together,
              "speedup": round(together["windows_per_s"] / apart["windows_per_s"], 3)}
    out = args.out or RESULTS / f"reader_step-{device.type}-{args.model}.json"
    write_result("reader_step.py", argv, result, out)
    print(f"{args.model}: {apart['step_ms']} ms a step in two passes, {together['step_ms']} ms as one batch "
          f"({result['speedup']}x)")
    return result


if __name__ == "__main__":
    main()
