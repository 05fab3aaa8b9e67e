"""A window set as the shapes a frozen regressor predicts: what readers train on under ``train.shared_regressor``.

In the bottleneck recipe the class loss never reaches the CNN (``learn.models``): the CNN and its lattice
head are a pixels -> cloth-shape regressor, and the models differ only in how they read the shape. With a
shared regressor, one model trains its own CNN and every other model of the same (setting, variant, seed)
takes it frozen, so their readers see the same predicted shapes every epoch. ``ShapeSet`` computes those
once, in evaluation mode and unaugmented, as prediction will see them, and serves them like a
``WindowSet``: an epoch of a reader is a few small matrix products instead of the CNN over every frame.
"""

from __future__ import annotations

from typing import Iterator

import pandas as pd
import torch

from learn.models import ClipClassifier, ShapeReader
from learn.windows import WindowSet, epoch_order, prediction_frame


class ShapeSet:
    """The windows of ``windows`` as ``regressor``'s predicted (T, geometry_dim) shapes, on the same device,
    with the windows' labels and true lattices."""

    resident = True

    def __init__(self, windows: WindowSet, regressor: ClipClassifier, batch_size: int, amp: bool):
        if windows.targets is None:
            raise ValueError("a shape set needs the windows' true lattices (train.bottleneck=true)")
        self.device, self.clip_len = windows.device, windows.clip_len
        self.clip_ids, self.starts, self.labels = windows.clip_ids, windows.starts, windows.labels
        shapes, lattices = [], []
        training = regressor.training
        regressor.eval()
        with torch.no_grad(), torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=amp):
            for x, _, lattice in windows.batches(batch_size):
                # .float() as the model's own forward does before its readers see the shape
                shapes.append(regressor.predicted_shape(x).float())
                lattices.append(lattice)
        regressor.train(training)
        width = regressor.geometry_dim
        empty = torch.zeros(0, self.clip_len, width, device=self.device)
        self.shapes = torch.cat(shapes) if shapes else empty
        self.targets = torch.cat(lattices) if lattices else empty
        self.device_labels = self.labels.to(self.device)

    @classmethod
    def of_tensors(cls, shapes: torch.Tensor, labels: torch.Tensor, targets: torch.Tensor) -> ShapeSet:
        """A shape set of given (N, T, geometry_dim) shapes and true lattices and (N,) labels, on the shapes'
        device, without a regressor or windows (benchmarks/reader_step.py, the graphed reader's GPU tests); its
        windows are named w0, w1, ... and start at frame 0."""
        self = cls.__new__(cls)
        self.device, self.clip_len = shapes.device, shapes.shape[1]
        self.clip_ids = [f"w{i}" for i in range(len(shapes))]
        self.starts = torch.zeros(len(shapes), dtype=torch.long)
        self.labels = labels.cpu()
        self.shapes, self.targets, self.device_labels = shapes, targets.to(shapes.device), labels.to(shapes.device)
        return self

    def __len__(self) -> int:
        return len(self.clip_ids)

    def order(self, seed: int, epoch: int, rank: int = 0, world: int = 1) -> torch.Tensor:
        """The epoch's window order, the same as the ``WindowSet``'s of the same windows."""
        return epoch_order(len(self), seed, epoch, rank, world)

    def batches(self, batch_size: int, *, order: torch.Tensor | None = None, drop_last: bool = False
                ) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """(shapes (B, T, geometry_dim), labels (B,), true lattices (B, T, geometry_dim)) on the device."""
        order = torch.arange(len(self)) if order is None else order
        # one copy an epoch, from pinned memory: the host does not wait for the GPU (learn.windows)
        order = (order.pin_memory() if self.device.type == "cuda" else order).to(self.device, non_blocking=True)
        stop = len(order) - (len(order) % batch_size if drop_last and len(order) >= batch_size else 0)
        for lo in range(0, stop, batch_size):
            idx = order[lo:lo + batch_size]
            yield self.shapes[idx], self.device_labels[idx], self.targets[idx]

    def predict(self, model: ClipClassifier, batch_size: int = 256, amp: bool | None = None) -> pd.DataFrame:
        """``model``'s readers' prediction frame (``learn.predictions``) on every window, in order, in eval mode:
        what the whole model predicts from the frames, the shapes being its frozen regressor's."""
        return prediction_frame(self, ShapeReader(model).eval(), model.probs, batch_size, amp)
