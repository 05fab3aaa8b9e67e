"""The learn stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TrainConfig:
    models: tuple[str, ...] = ("lrcn",)     # "lrcn", "base1", "base2", "base3"
    seeds: tuple[int, ...] = (0,)
    image_size: int = 64                    # frames are resized to this before the CNN
    clip_len: int = 10                      # frames per sub-sequence (the paper: 10)
    clip_stride: int = 5                    # start-frame step between sub-sequences of one sequence
    val_fraction: float = 0.1
    test_fraction: float = 1 / 6            # the paper: 432 of 2,592 sequences
    epochs: int = 10
    batch_size: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    width: int = 32                         # channels of conv1; later layers scale from it
    fc6: int = 256
    hidden: int = 128                       # LSTM / RNN hidden size
    augment: bool = False
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
    num_workers: int = 0                    # DataLoader worker processes
