"""A reader's training step (the readers of a shared regressor): the predicted and the true shape read as one batch
against one after another.

    python benchmarks/reader_step.py [--device auto] [--model base2] [--batch-size 16] [--frames 40] [--steps 200]
                                     [--warmup 20] [--out FILE]

Under ``train.shared_regressor`` base1-3 train their readers alone on the regressor's cached shapes, with
``train.reader_truth`` reading the simulation's own lattice as well: two passes through the readers a step.
``ClipClassifier.read_shape`` reads both as one batch (the same sums a clip: tests/test_learn_models.py). This
times the `paper` preset's reader (its model arguments, optimiser, truth weight and bf16 on CUDA, through
``learn.train.run_epoch``) on random shapes held on the device, both ways in one process from the same weights,
and writes the ms a step, windows/s and their ratio to benchmarks/results/reader_step-<device>-<model>.json with
the command. On CUDA it also times the one-batch step captured once as a CUDA graph and replayed
(``train.reader_graphs``, ``learn.steps.GraphedReaderEpochs``), on ``--steps`` distinct batches, against the
eager one-batch step (``graphed_over_one_batch``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, torch_device, write_result  # noqa: E402  (benchmarks/common.py)
from clothgap.config import preset  # noqa: E402
from learn.models import GEOMETRY_DIM, NUM_CLASSES, ShapeReader, build_model, model_args  # noqa: E402
from learn.shapes import ShapeSet  # noqa: E402
from learn.steps import GraphedReaderEpochs  # noqa: E402
from learn.train import make_optimizer, resolve_device, run_epoch  # noqa: E402


class ReadApart(torch.nn.Module):
    """``ShapeReader`` with ``read_shape`` as two passes through the readers, the predicted shape and then the true
    one (how a reader's step read them before)."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, geometry: torch.Tensor, lattice: torch.Tensor) -> dict[str, torch.Tensor]:
        model = self.model
        out = model.read_lattice(model._noised(geometry.detach().float()))
        out["truth_logits"] = model.read_lattice(model._noised(lattice.float()))["logits"]
        return out


def main(argv: list[str] | None = None) -> dict:
    cfg = preset("paper").train
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--model", default="base2", choices=("base1", "base2", "base3"))
    ap.add_argument("--batch-size", type=int, default=cfg.batch_size)
    ap.add_argument("--frames", type=int, default=cfg.clip_len)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    amp = cfg.amp and device.type == "cuda"
    gen = torch.Generator().manual_seed(0)
    shape = torch.randn(args.batch_size, args.frames, GEOMETRY_DIM, generator=gen).to(device)
    lattice = torch.randn(args.batch_size, args.frames, GEOMETRY_DIM, generator=gen).to(device)
    labels = torch.randint(0, NUM_CLASSES, (args.batch_size,), generator=gen).to(device)

    def reader() -> tuple:
        """The reader at the same starting weights each time, and its optimiser."""
        torch.manual_seed(0)
        model = build_model(args.model, **model_args(cfg)).to(device)
        model.cnn.requires_grad_(False)             # a shared regressor's readers train alone (take_regressor)
        model.head_geometry.requires_grad_(False)
        return model, make_optimizer(model, cfg, device)

    def rates(seconds: float) -> dict:
        return {"step_ms": round(1000 * seconds / args.steps, 3),
                "windows_per_s": round(args.steps * args.batch_size / seconds, 1)}

    def timed(one_batch: bool) -> dict:
        model, optimizer = reader()
        net = ShapeReader(model) if one_batch else ReadApart(model)

        def steps(n: int) -> None:      # the training step itself; run_epoch reads its sums back at the end
            run_epoch(net, model, [(shape, labels, lattice)] * n, device, optimizer, amp,
                      label_smoothing=cfg.label_smoothing, truth_weight=cfg.reader_truth)

        steps(args.warmup)
        start = time.perf_counter()
        steps(args.steps)
        return rates(time.perf_counter() - start)

    def graphed() -> dict:
        """The one-batch step captured as a CUDA graph and replayed (train.reader_graphs, learn.steps), on
        ``--steps`` distinct batches of random shapes held on the device."""
        model, optimizer = reader()
        n = args.batch_size * max(args.steps, args.warmup)
        data = ShapeSet.of_tensors(torch.randn(n, args.frames, GEOMETRY_DIM, generator=gen).to(device),
                                   torch.randint(0, NUM_CLASSES, (n,), generator=gen),
                                   torch.randn(n, args.frames, GEOMETRY_DIM, generator=gen))
        epochs = GraphedReaderEpochs(ShapeReader(model), model, optimizer, data, args.batch_size, device, amp,
                                     label_smoothing=cfg.label_smoothing, truth_weight=cfg.reader_truth)
        epochs.epoch(torch.arange(args.batch_size * args.warmup))      # warm-up and capture
        start = time.perf_counter()
        epochs.epoch(torch.arange(args.batch_size * args.steps))
        return {**rates(time.perf_counter() - start), "captured": epochs.graph is not None,
                "capture_failed": epochs.failed}

    apart = timed(one_batch=False)
    together = timed(one_batch=True)
    result = {**torch_device(device), "threads": torch.get_num_threads(), "model": args.model,
              "batch_size": args.batch_size, "frames": args.frames, "warmup": args.warmup, "steps": args.steps,
              "two_passes": apart, "one_batch": together,
              "speedup": round(together["windows_per_s"] / apart["windows_per_s"], 3)}
    if device.type == "cuda":
        result["graphed"] = replay = graphed()
        result["graphed_over_one_batch"] = round(replay["windows_per_s"] / together["windows_per_s"], 3)
        print(f"{args.model}: graphed {replay['step_ms']} ms a step ({result['graphed_over_one_batch']}x the one "
              f"batch step){'' if replay['captured'] else ', not captured: ' + str(replay['capture_failed'])}")
    out = args.out or RESULTS / f"reader_step-{device.type}-{args.model}.json"
    write_result("reader_step.py", argv, result, out)
    print(f"{args.model}: {apart['step_ms']} ms a step in two passes, {together['step_ms']} ms as one batch "
          f"({result['speedup']}x)")
    return result


if __name__ == "__main__":
    main()
