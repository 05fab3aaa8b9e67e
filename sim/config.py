"""The sim stage's settings (no heavy imports here: the CLI reads this at start-up)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SimConfig:
    # The simulated settings: every (motion, remeshing) pair is one dataset.
    motions: tuple[str, ...] = ("wind",)            # "wind", "arm"
    remeshing: tuple[str, ...] = ("uniform1",)      # "uniform1", "uniform2", "uniform3", "adaptive"
    # Material classes simulated (indices into sim.classes, 0..53); empty = all 54.
    classes: tuple[int, ...] = ()
    sequences_per_class: int = 48                   # 54 x 48 = 2,592, the paper's dataset size
    basis: str = "camel-ponte-roma"                 # the paper's basis material
    jitter: float = 0.1                             # relative jitter of (p, k) around the class value
    grid_vertices: int = 16                         # vertices per side at uniform level 1
    cloth_size_m: float = 0.5                       # side of the square cloth, metres
    frames: int = 20                                # frames written per sequence
    fps: float = 25.0
    substeps: int = 8                               # solver steps per frame
    settle_s: float = 0.4                           # simulated seconds before the first recorded frame
    cg_iterations: int = 30                         # conjugate-gradient iterations per solver step
    device: str = "auto"                            # "auto", "cpu", "cuda", "cuda:N"
    batch_size: int = 512                           # cloths advanced together in one launch

    def class_indices(self) -> tuple[int, ...]:
        return self.classes or tuple(range(54))

    def settings(self) -> list[str]:
        """Dataset names, one per (motion, remeshing): e.g. 'wind-uniform1'."""
        return [f"{m}-{r}" for m in self.motions for r in self.remeshing]

    def num_clips(self) -> int:
        return len(self.class_indices()) * self.sequences_per_class
