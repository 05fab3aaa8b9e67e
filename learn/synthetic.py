"""Stand-in rendered clips with a learnable signal, for tests, timings and benchmarks.

Writes folders in the render stage's on-disk format (``ldr/%04d.png``,
``meta.json``, ``DONE``) so the learn stage can be exercised before, or without,
sim and render. Each clip is a textured background with a bright blob that
sways: the blob's size follows the stretching index and its sway amplitude the
bending index of the class (stiffer, less sway), so one frame shows the first
and the motion, or the spread of positions over frames, the second.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from clothgap import seeding
from clothgap.runs import Run, atomic_write_json, clip_id, mark_done

NUM_BEND = 9


def synthetic_frames(class_index: int, frames: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """(frames, size, size, 3) uint8 frames of one synthetic sequence of ``class_index``."""
    p_index, k_index = divmod(class_index, NUM_BEND)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    # Nuisances vary per sequence (background shade and texture, blob tint, phase),
    # but stay small next to the class signal so that a few sequences per class suffice.
    background = rng.uniform(0.1, 0.3, size=(1, 1, 3)) + 0.04 * rng.standard_normal((size, size, 3))
    radius = 0.10 + 0.05 * p_index
    amplitude = 0.30 - 0.03 * k_index      # stiffer in bending, less sway
    freq = rng.uniform(0.10, 0.14)         # cycles per frame
    phase = rng.uniform(0, 2 * np.pi)
    colour = rng.uniform(0.85, 0.95, size=3)
    out = np.empty((frames, size, size, 3), np.uint8)
    for t in range(frames):
        cx = 0.5 + amplitude * np.sin(2 * np.pi * freq * t + phase)
        cy = 0.5 + 0.3 * amplitude * np.cos(2 * np.pi * freq * t + phase)
        blob = (((xx - cx) ** 2 + (yy - cy) ** 2) < radius ** 2)[..., None]
        img = np.where(blob, colour, background) + 0.02 * rng.standard_normal((size, size, 3))
        out[t] = np.clip(img * 255, 0, 255).astype(np.uint8)
    return out


def write_synthetic_clip(folder: Path, index: int, class_index: int, frames: int, size: int,
                         seed: int = 0, variant: str = "synthetic", setting: str = "synthetic") -> Path:
    """One finished clip folder in the render format (frames, meta.json, DONE last)."""
    rng = seeding.rng(seed, index, seeding.RENDER, "synthetic", variant)
    (folder / "ldr").mkdir(parents=True, exist_ok=True)
    for t, frame in enumerate(synthetic_frames(class_index, frames, size, rng)):
        Image.fromarray(frame).save(folder / "ldr" / f"{t:04d}.png")
    p_index, k_index = divmod(class_index, NUM_BEND)
    atomic_write_json(folder / "meta.json", {
        "clip_id": clip_id(index), "index": index, "setting": setting, "variant": variant,
        "class_index": class_index, "p_class": p_index, "k_class": k_index,
        "p": float(p_index), "k": float(k_index), "num_frames": frames, "status": "ok"})
    mark_done(folder)
    return folder


def synthetic_run(root: Path | str, config: Any) -> Run:
    """A run whose render folders hold synthetic clips shaped by ``config`` (a ``clothgap.config.StudyConfig``).

    Classes, sequences per class and frames come from ``config.sim``, the frame
    size from ``config.render.resolution``; every variant and setting is written.
    """
    run = Run.create_or_resume(Path(root), config)
    classes = config.sim.class_indices()
    labels = [c for c in classes for _ in range(config.sim.sequences_per_class)]
    for variant in config.render.variants:
        for setting in config.sim.settings():
            for index, label in enumerate(labels):
                folder = run.render_dir(variant, setting) / clip_id(index)
                if not (folder / "DONE").is_file():
                    write_synthetic_clip(folder, index, label, config.sim.frames, config.render.resolution,
                                         config.seed, variant, setting)
    return run
