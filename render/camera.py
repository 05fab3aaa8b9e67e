"""Camera effects applied to the composited linear frame before tone mapping.

A real camera is not a perfect radiance meter: its exposure and white balance
are off by a clip-dependent amount, its lens darkens the corners (vignetting),
and its sensor adds shot and read noise. Each effect is off at 0 (the paper's
setting). Per-clip errors come from the ``camera`` stream and per-frame noise
from the ``noise`` stream, so enabling one never moves the draws of another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from render.variants import RenderVariant


@dataclass(frozen=True)
class CameraState:
    """The per-clip draws: one exposure gain and one white-balance gain per channel."""

    gain: float
    white_balance: tuple[float, float, float]

    def info(self) -> dict:
        return {"gain": self.gain, "white_balance": list(self.white_balance)}


def draw_camera(variant: RenderVariant, rng: np.random.Generator) -> CameraState:
    """The clip's exposure and white-balance errors (always drawn, so the stream's use is fixed)."""
    stops = variant.exposure_stops + variant.exposure_jitter_stops * rng.uniform(-1.0, 1.0)
    wb = 1.0 + variant.white_balance_jitter * rng.uniform(-1.0, 1.0, 3)
    return CameraState(float(2.0 ** stops), tuple(float(g) for g in wb))


def adds_noise(variant: RenderVariant) -> bool:
    return variant.shot_noise > 0 or variant.read_noise > 0


def camera_gain(state: CameraState) -> np.ndarray:
    """The clip's exposure times white balance per channel, (3,) float32: the factor a composited frame gets."""
    return state.gain * np.asarray(state.white_balance, np.float32)


def vignette(variant: RenderVariant, h: int, w: int) -> np.ndarray | None:
    """The lens falloff per pixel, (h, w) float64, cos^4-like (corners lose the most); None without vignetting."""
    if variant.vignetting <= 0:
        return None
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x + 0.5) / w - 0.5) ** 2 + ((y + 0.5) / h - 0.5) ** 2
    return 1.0 - variant.vignetting * (r2 / 0.5)


def apply_camera(linear: np.ndarray, variant: RenderVariant, state: CameraState,
                 noise_rng: np.random.Generator | None) -> np.ndarray:
    """Linear RGB (H, W, 3) as the camera records it: exposure, white balance, vignetting, noise.

    ``noise_rng`` is the frame's noise stream; it may be None when the variant adds no noise."""
    image = linear * camera_gain(state)
    falloff = vignette(variant, *image.shape[:2])
    if falloff is not None:
        image = image * falloff[..., None]
    if adds_noise(variant):
        variance = variant.shot_noise * np.maximum(image, 0.0) + variant.read_noise ** 2
        image = image + noise_rng.normal(size=image.shape) * np.sqrt(variance)
    return np.maximum(image, 0.0).astype(np.float32, copy=False)
