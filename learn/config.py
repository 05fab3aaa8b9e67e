"""The learn stage's settings (no heavy imports here).

The names the learn stage supports live here or in ``learn.registry`` (the
models), so that a config is checked without importing torch:
``learn.models`` builds the registered models with a readout from
``READOUTS``, ``learn.train`` runs the ``SCHEDULES``.
"""

from __future__ import annotations

from dataclasses import dataclass

from clothgap import checks
from learn.registry import MODEL_NAMES, get_model_entry

READOUTS = ("mean", "last")
SCHEDULES = ("cosine", "step")
KEEP = ("last", "best")                             # which epoch's weights become checkpoint.pt
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune-no-cudagraphs", "max-autotune")   # torch.compile's
SPLIT_BY = ("sequence", "subsequence")              # learn.split: whole sequences, or the paper's leaky windows
IMAGE_SIZES = range(32, 225, 16)                    # FrameCNN: a multiple of 16 from 32 to 224
GEOMETRY_CENTRES = ("median", "frame")              # learn.geometry: what a lattice target is measured from


@dataclass(frozen=True)
class TrainConfig:
    models: tuple[str, ...] = ("lrcn",)     # names in learn.registry: "lrcn", "base1", "base2", "base3"
    seeds: tuple[int, ...] = (0,)
    image_size: int = 64                    # frames are resized to this before the CNN
    clip_len: int = 10                      # frames per sub-sequence (the paper: 10)
    clip_stride: int = 5                    # start-frame step between sub-sequences of one sequence
    val_fraction: float = 0.1
    test_fraction: float = 1 / 6            # the paper: 432 of 2,592 sequences
    split_by: str = "sequence"              # "sequence", or "subsequence": the paper's protocol, which leaks
                                            # (windows of one simulation on both sides; learn.split)
    epochs: int = 10
    batch_size: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    width: int = 32                         # channels of conv1; later layers scale from it
    fc6: int = 256
    hidden: int = 128                       # LSTM / RNN hidden size
    augment: bool = False
    augment_crop: bool = True               # with augment: its random resized crop and flip (false: only the
                                            # temporal shift and colour jitter, which keep the lattice target aligned)
    augment_camera: bool = False            # camera errors per clip, with or without augment (camera_augment_batch)
    device: str = "auto"
    num_threads: int = 0                    # torch CPU threads, 0 = torch's default
    schedule: str = "cosine"                # learning-rate schedule over epochs: "cosine" or "step"
    readout: str = "mean"                   # "mean": loss on every step, probabilities averaged (LRCN);
                                            # "last": loss and prediction from the last step only
    dropout: float = 0.5                    # on fc6, as in AlexNet
    factored: bool = False                  # extra 6-way stretching and 9-way bending heads
    pretrained: str = ""                    # local weights file for the CNN; never downloaded
    amp: bool = True                        # bf16 autocast (CUDA only; ignored on CPU)
    compile: bool = False                   # torch.compile the model (CUDA only; ignored on CPU)
    compile_mode: str = "default"           # its mode: "reduce-overhead" replays CUDA graphs, which removes the
                                            # per-step launch cost that bounds a small batch on a large GPU
    compile_readers: bool = True            # with train.shared_regressor, compile the readers on its frozen
                                            # shapes too (under graphs base2/base3's recurrent layers ran
                                            # 1.1-1.6x slower: docs/learning.md)
    reader_graphs: bool = False             # with train.shared_regressor, the readers' whole training step
                                            # (batch, forward, backward, update) captured once as a CUDA graph
                                            # and replayed (learn.steps); the readers are then not compiled
    num_workers: int = 0                    # unused: batches are cut from frames held on the device
                                            # (learn.windows); kept so that older run folders load
    motion: bool = False                    # frame differences beside the frames (6 input channels)
    aux_geometry: float = 0.0               # weight of the auxiliary lattice regression (learn.geometry)
    label_smoothing: float = 0.0
    keep: str = "last"                      # "last" epoch, or the "best" epoch by validation accuracy
    bottleneck: bool = False                # classes read only the CNN's predicted lattice (learn.models);
                                            # the lattice loss weighs aux_geometry (1 when left at 0)
    bottleneck_noise: float = 0.0           # std of noise on that lattice while training (standardised units)
    conv5_pool: bool = True                 # AlexNet's max-pool after conv5; false: fc6 reads conv5's own
                                            # map (size/16, at most 7 x 7; 7 x 7 at 112 px instead of 3 x 3)
    geometry_window: int = 1                # frames the lattice head reads (odd; 1: its own frame only)
    reader_truth: float = 0.0               # weight of the bottleneck readers' class loss on the simulation's
                                            # own lattice (noised by bottleneck_noise), beside the predicted one
    shared_regressor: str = ""              # a model whose trained CNN and lattice head every other model takes,
                                            # frozen: their readers train on its predicted lattices, computed
                                            # once (bottleneck only; "": each model trains its own CNN)
    reader_epochs: int = 0                  # epochs of the models that read a shared regressor (0: train.epochs):
                                            # a reader's epoch costs little, and readers on noisy shapes learn
                                            # for longer (docs/learning.md)
    train_fraction: float = 1.0             # share of each class's training sequences used (a nested, seeded
                                            # draw; validation and test unchanged): the data-size learning curve
    geometry_centre: str = "median"         # lattice targets from the median shape of all frames, or "frame":
                                            # from the median shape at the same frame index, which takes out of
                                            # the target what every material shares (the arm's sweep)

    @property
    def geometry_weight(self) -> float:
        """The weight of the lattice loss: ``aux_geometry``, or 1 for a bottleneck left at 0."""
        return self.aux_geometry or (1.0 if self.bottleneck else 0.0)

    def problems(self) -> list[str]:
        """What is wrong with these settings, one message each (empty when they are valid)."""
        out = checks.names("train.models", self.models, MODEL_NAMES, "model")
        if not self.seeds:
            out.append("train.seeds is empty; give at least one seed, e.g. train.seeds=0")
        out += checks.names("train.seeds", self.seeds, self.seeds, "seed", required=False)
        out += [f"train.seeds: seed {s} is negative" for s in self.seeds if s < 0]
        if self.image_size not in IMAGE_SIZES:
            out.append(f"train.image_size={self.image_size!r}: must be a multiple of 16 from "
                       f"{IMAGE_SIZES.start} to {IMAGE_SIZES.stop - 1}")
        out += checks.number("train.clip_len", self.clip_len, 1)
        out += checks.number("train.clip_stride", self.clip_stride, 1)
        out += checks.number("train.val_fraction", self.val_fraction, 0, 1, hi_open=True)
        out += checks.number("train.test_fraction", self.test_fraction, 0, 1, hi_open=True)
        if self.val_fraction + self.test_fraction >= 1:
            out.append(f"train.val_fraction={self.val_fraction:g} + train.test_fraction={self.test_fraction:g} "
                       "leaves nothing to train on: their sum must be < 1")
        out += checks.choice("train.split_by", self.split_by, SPLIT_BY)
        if self.split_by == "subsequence" and self.clip_stride < self.clip_len:
            out.append(f"train.split_by=subsequence needs train.clip_stride >= train.clip_len ({self.clip_len}), "
                       f"got {self.clip_stride}: overlapping windows would share frames across train and test")
        out += checks.number("train.epochs", self.epochs, 1)
        out += checks.number("train.batch_size", self.batch_size, 1)
        out += checks.number("train.lr", self.lr, 0, lo_open=True)
        out += checks.number("train.weight_decay", self.weight_decay, 0)
        out += checks.number("train.width", self.width, 1)
        out += checks.number("train.fc6", self.fc6, 1)
        out += checks.number("train.hidden", self.hidden, 1)
        out += checks.number("train.dropout", self.dropout, 0, 1, hi_open=True)
        out += checks.choice("train.schedule", self.schedule, SCHEDULES)
        out += checks.choice("train.readout", self.readout, READOUTS)
        out += checks.device("train.device", self.device, extra=("mps",))
        out += checks.number("train.num_threads", self.num_threads, 0)
        out += checks.number("train.num_workers", self.num_workers, 0)
        out += checks.number("train.aux_geometry", self.aux_geometry, 0)
        out += checks.number("train.label_smoothing", self.label_smoothing, 0, 1, hi_open=True)
        out += checks.choice("train.keep", self.keep, KEEP)
        out += checks.choice("train.compile_mode", self.compile_mode, COMPILE_MODES)
        out += checks.number("train.bottleneck_noise", self.bottleneck_noise, 0)
        if self.bottleneck_noise and not self.bottleneck:
            out.append("train.bottleneck_noise is set but train.bottleneck is off; set train.bottleneck=true")
        out += checks.number("train.reader_truth", self.reader_truth, 0)
        out += checks.number("train.train_fraction", self.train_fraction, 0, 1, lo_open=True)
        out += checks.number("train.geometry_window", self.geometry_window, 1)
        out += checks.choice("train.geometry_centre", self.geometry_centre, GEOMETRY_CENTRES)
        if isinstance(self.geometry_window, int) and self.geometry_window % 2 == 0:
            out.append(f"train.geometry_window={self.geometry_window}: must be odd (the frame itself and as many "
                       "frames before it as after it)")
        if self.reader_truth and not self.bottleneck:
            out.append("train.reader_truth is set but train.bottleneck is off; set train.bottleneck=true")
        if self.shared_regressor:
            if self.shared_regressor not in MODEL_NAMES:
                out.append(f"train.shared_regressor={self.shared_regressor!r}: must be one of the models "
                           f"({', '.join(MODEL_NAMES)}) or empty")
            elif needs := get_model_entry(self.shared_regressor).needs:
                out.append(f"train.shared_regressor={self.shared_regressor!r}: that model starts from "
                           f"{needs}'s CNN; name a model that trains its own")
            if not self.bottleneck:
                out.append("train.shared_regressor is set but train.bottleneck is off: only a bottleneck model's "
                           "classes read nothing of the CNN but its lattice; set train.bottleneck=true, or "
                           "train.shared_regressor= (empty: every model its own CNN; the paper preset sets lrcn)")
        out += checks.number("train.reader_epochs", self.reader_epochs, 0)
        if self.reader_epochs and not self.shared_regressor:
            out.append("train.reader_epochs is set but train.shared_regressor is not: only readers on a shared "
                       "regressor train apart from their CNN")
        if self.keep == "best" and self.val_fraction <= 0:
            out.append("train.keep=best needs validation clips: set train.val_fraction > 0")
        return out
