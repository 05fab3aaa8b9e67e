"""Tiny runs shared by the test files (imported as ``from tests.conftest import ...``).

Each is the smallest study that still exercises a stage for real: a few classes, a few frames, a small grid
and a small network, on the CPU.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from clothgap.config import StudyConfig, preset
from clothgap.runs import Run, clip_id, mark_done
from learn.config import TrainConfig
from render.config import RenderConfig
from render.synthetic import waving_sheet
from sim.config import SimConfig

SETTING, VARIANT = "wind-uniform1", "paper"
RENDER_BACKEND = "scalar_rgb"       # no LLVM or GPU needed, and the same pixels on every machine


def coarse_analysis_setup():
    """sim.analysis's set-up on coarse meshes, a short sweep and a short settle (Table 2 and the sensitivity curves
    in seconds): the properties the tests check hold at any resolution."""
    from sim.analysis import Setup

    return Setup(hang_vertices=6, strip_length=0.03, strip_vertices=11, seconds=1.0, average_seconds=0.2,
                 samples=2, sweep=tuple(np.geomspace(1 / 64, 4, 9)))


def tiny_sim_run(root: Path, seed: int = 0, render: RenderConfig | None = None, **sim) -> Run:
    """A new run of a clip per class (classes 0 and 53 unless ``sim`` says otherwise), three frames on a 6x6 grid
    on the CPU: a second or two to simulate on one core. ``sim`` overrides sim settings, ``render`` replaces the
    render config."""
    cfg = StudyConfig(name="tiny", seed=seed, sim=SimConfig(**{
        "classes": (0, 53), "sequences_per_class": 1, "grid_vertices": 6, "frames": 3, "settle_s": 0.04,
        "device": "cpu", "batch_size": 4, **sim}), **({"render": render} if render is not None else {}))
    cfg = replace(cfg, train=replace(cfg.train, clip_len=min(cfg.train.clip_len, cfg.sim.frames)))
    return Run.create_or_resume(root, cfg)


def synthetic_sim_run(root: Path, variants=("paper",), clips: int = 2, frames: int = 3, remeshing=("uniform1",),
                      **render) -> Run:
    """A run of the smoke preset whose sim folders hold ``clips`` finished synthetic clips per setting
    (``render.synthetic.waving_sheet``), ready to render at 16 px, 1 spp on the scalar backend; ``render``
    overrides render settings."""
    cfg = preset("smoke")
    cfg = replace(cfg, sim=replace(cfg.sim, frames=frames, remeshing=remeshing),
                  render=replace(cfg.render, variants=variants, resolution=16, spp=1,
                                 **{"backend": RENDER_BACKEND, **render}))
    cfg = replace(cfg, train=replace(cfg.train, clip_len=min(cfg.train.clip_len, frames)))
    run = Run.create_or_resume(root, cfg)
    for setting in cfg.sim.settings():
        for i in range(clips):
            folder = run.sim_dir(setting) / clip_id(i)
            waving_sheet(frames=frames, n=8, index=i, setting=setting).save(folder)
            mark_done(folder)
    return run


def tiny_train_config(**train) -> StudyConfig:
    """Four classes at the corners of the (p, k) grid, short clips, a very small network; ``train`` overrides
    train settings."""
    base = dict(image_size=32, clip_len=6, clip_stride=5, epochs=3, batch_size=8, width=8, fc6=32, hidden=16,
                dropout=0.2, val_fraction=0.25, test_fraction=0.25, lr=3e-3, num_threads=2)
    return StudyConfig(sim=SimConfig(classes=(0, 8, 45, 53), sequences_per_class=4, frames=16),
                       render=RenderConfig(resolution=32), train=TrainConfig(**{**base, **train}))


def flat_sheet(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The uv (n*n, 2) and the flat rest positions (n*n, 3) of an n x n vertex sheet, row by row."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    uv = np.stack([u.ravel(), v.ravel()], -1).astype(np.float32)
    return uv, np.concatenate([uv, np.zeros((n * n, 1), np.float32)], 1)
