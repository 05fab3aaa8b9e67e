"""A training step, and the readers' epochs replayed from one CUDA graph (``train.reader_graphs``).

The readers of a shared regressor (``learn.shapes``) train on small tensors already on the GPU: a step is a few
hundred tiny kernels, and launching them from Python costs more than running them (base2 3.64 ms a step on an
H100, 0.64 ms graphed: ``benchmarks/reader_step.py``, ``benchmarks/results/reader_step-graphed-cuda-base2-h100.json``). ``GraphedReaderEpochs`` captures the whole step, the batch cut from the
cached shapes by an index buffer, forward, loss, backward and the optimiser's update, once, and replays it for
every batch: one launch a step. torch.compile's graphs (``train.compile_readers``) ran base2's and base3's
recurrent readers slower instead (docs/learning.md).

Every batch trains exactly once, in the epoch's order: the first steps of a training run eagerly on a side
stream (what capture needs: lazily made state, cuDNN's choices), then the next is captured (capture runs
nothing) and replayed. Replays draw the bottleneck's noise from the same generator, so a graphed training is as
reproducible as an eager one, not the same draws; its rounding is the eager step's.
"""

from __future__ import annotations

import math
import warnings

import torch

from learn.models import ClipClassifier
from learn.shapes import ShapeSet

WARMUP_STEPS = 3


def train_step(net: torch.nn.Module, model: ClipClassifier, x: torch.Tensor, y: torch.Tensor,
               target: torch.Tensor | None, device: torch.device, optimizer, amp: bool, sums: torch.Tensor, *,
               geometry_weight: float = 0.0, label_smoothing: float = 0.0, truth_weight: float = 0.0,
               autocast_cache: bool = True) -> None:
    """One batch forward (and, with ``optimizer``, backward and update; the gradients zeroed by the caller), its
    loss x clips, correct clips, clips and lattice squared error x clips added to ``sums`` on the device."""
    training = optimizer is not None
    # (a graph cannot hold autocast's cache of cast weights: torch.cuda.graph's rules)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp, cache_enabled=autocast_cache):
        out = net(x, target) if training and truth_weight else net(x)
    loss = model.loss(out, y, geometry=target, geometry_weight=geometry_weight,
                      label_smoothing=label_smoothing if training else 0.0, truth_weight=truth_weight)
    if training:
        loss.backward()
        optimizer.step()
    # In place with Python scalars: a tensor made from a number would be a blocking copy to the device, a wait
    # for the GPU every step.
    n = len(y)
    sums[0] += loss.detach().double() * n
    sums[1] += (model.probs(out).argmax(-1) == y).sum()
    sums[2] += n
    sums[3] += (((out["geometry"].detach().float() - target) ** 2).mean().double() * n
                if target is not None and "geometry" in out else math.nan)


def make_capturable(optimizer: torch.optim.Optimizer, device: torch.device) -> None:
    """Let ``optimizer.step`` be captured: its step counts on the device (``capturable``) and its learning rate a
    device tensor that the schedule fills in place, so that a replayed update reads the epoch's rate (a Python
    float would be frozen into the graph). Idempotent; after a resume too (``load_state_dict`` restores the
    saved groups)."""
    for group in optimizer.param_groups:
        group["capturable"] = True
        lr = group["lr"]
        # A tensor on another device is one too: last.pt is read onto the CPU, and a CPU rate goes to the fused
        # kernel as a number, which capture would freeze at the resumed epoch's value.
        if not (torch.is_tensor(lr) and lr.device == device and lr.dtype == torch.float32):
            group["lr"] = torch.tensor(float(lr), dtype=torch.float32, device=device)
    for state in optimizer.state.values():
        if "step" in state and torch.is_tensor(state["step"]) and state["step"].device != device:
            state["step"] = state["step"].to(device)


class GraphedReaderEpochs:
    """A reader's training epochs on a ``ShapeSet`` as replays of one captured step (CUDA only, one process)."""

    def __init__(self, net: torch.nn.Module, model: ClipClassifier, optimizer: torch.optim.Optimizer, shapes: ShapeSet,
                 batch_size: int, device: torch.device, amp: bool, *, geometry_weight: float = 0.0,
                 label_smoothing: float = 0.0, truth_weight: float = 0.0):
        if device.type != "cuda":
            raise ValueError("graphed epochs replay CUDA graphs: a CUDA device only")
        self.net, self.model, self.optimizer, self.shapes = net, model, optimizer, shapes
        self.batch_size, self.device, self.amp = batch_size, device, amp
        self.geometry_weight, self.label_smoothing, self.truth_weight = geometry_weight, label_smoothing, truth_weight
        self.index = torch.zeros(batch_size, dtype=torch.long, device=device)
        self.sums = torch.zeros(4, dtype=torch.float64, device=device)
        self.graph: torch.cuda.CUDAGraph | None = None
        self.eager_steps = 0
        self.failed: str | None = None      # why capture failed: the training goes on eagerly
        make_capturable(optimizer, device)

    def _step(self) -> None:
        s, idx = self.shapes, self.index
        train_step(self.net, self.model, s.shapes[idx], s.device_labels[idx], s.targets[idx], self.device,
                   self.optimizer, self.amp, self.sums, geometry_weight=self.geometry_weight,
                   label_smoothing=self.label_smoothing, truth_weight=self.truth_weight, autocast_cache=False)

    def _eager(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        self._step()

    def _warm_up(self, side: torch.cuda.Stream) -> None:
        """An eager step on a side stream, as torch.cuda.graph asks before a capture."""
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            self._eager()
        torch.cuda.current_stream(self.device).wait_stream(side)
        self.eager_steps += 1

    def _capture(self) -> None:
        """Record the step (which runs nothing); if it cannot be captured, say why once (``failed``): the
        training goes on eagerly."""
        self.optimizer.zero_grad(set_to_none=True)      # the graph's backward writes the gradients it made
        graph = torch.cuda.CUDAGraph()
        stream = torch.cuda.current_stream(self.device)
        try:
            with torch.cuda.graph(graph):
                self._step()
        except Exception as e:     # an op that cannot be captured
            torch.cuda.set_stream(stream)        # (a capture that fails on its way out leaves its own stream set)
            self.failed = f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}"
            warnings.warn(f"the reader's step could not be captured as a CUDA graph ({self.failed}); it trains "
                          "eagerly", stacklevel=3)
            torch.cuda.synchronize(self.device)
            self.optimizer.zero_grad(set_to_none=True)
            return
        self.graph = graph

    def epoch(self, order: torch.Tensor) -> torch.Tensor:
        """Train on ``order``'s windows (whole batches; the last partial one dropped, as the eager epoch does);
        returns the epoch's sums (``learn.train.run_epoch``'s) on the host."""
        self.net.train(True)
        self.sums.zero_()
        order = order.to(self.device, non_blocking=True)
        side = torch.cuda.Stream(self.device)
        for k in range(len(order) // self.batch_size):
            self.index.copy_(order[k * self.batch_size:(k + 1) * self.batch_size])
            if self.graph is None and not self.failed and self.eager_steps >= WARMUP_STEPS:
                self._capture()
            if self.graph is not None:
                self.graph.replay()
            elif self.failed:
                self._eager()
            else:
                self._warm_up(side)
        return self.sums.cpu()
