"""Tone mapping: linear HDR radiance -> 8-bit sRGB, through named operators.

Each operator maps scene-linear values (>= 0, possibly far above 1) to display-
linear values in [0, 1], channel by channel, monotonically, with 0 -> 0; the
sRGB transfer function (colour-science) and 8-bit quantisation follow. Which
operator a variant uses is one of the study's axes: cameras do not clip, and a
network trained on clipped highlights may read real footage differently.
"""

from __future__ import annotations

from typing import Callable

import colour
import numpy as np

REINHARD_WHITE = 4.0        # the radiance that maps to display white under Reinhard
FILMIC_WHITE = 11.2         # Hable's linear white point
FILMIC_EXPOSURE_BIAS = 2.0  # Hable's usual pre-scale, so mid-grey stays mid-grey


def srgb_clip(x: np.ndarray) -> np.ndarray:
    """No compression: everything above 1 clips (what the paper's renders did)."""
    return np.clip(x, 0.0, 1.0)


def reinhard(x: np.ndarray) -> np.ndarray:
    """Extended Reinhard per channel, x (1 + x / w^2) / (1 + x): smooth roll-off reaching 1 at ``REINHARD_WHITE``."""
    x = np.maximum(x, 0.0)
    return np.clip(x * (1.0 + x / REINHARD_WHITE ** 2) / (1.0 + x), 0.0, 1.0)


def _hable(x: np.ndarray) -> np.ndarray:
    a, b, c, d, e, f = 0.15, 0.50, 0.10, 0.20, 0.02, 0.30
    return (x * (a * x + c * b) + d * e) / (x * (a * x + b) + d * f) - e / f


def filmic(x: np.ndarray) -> np.ndarray:
    """Hable's filmic curve (Uncharted 2) per channel: a toe in the shadows and a shoulder in the highlights."""
    x = np.maximum(x, 0.0)
    return np.clip(_hable(FILMIC_EXPOSURE_BIAS * x) / _hable(np.float64(FILMIC_WHITE)), 0.0, 1.0)


OPERATORS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "srgb_clip": srgb_clip, "reinhard": reinhard, "filmic": filmic,
}


def tonemap(linear_rgb: np.ndarray, operator: str) -> np.ndarray:
    """Scene-linear RGB (H, W, 3) -> 8-bit sRGB (H, W, 3) uint8 through ``operator``."""
    try:
        op = OPERATORS[operator]
    except KeyError:
        raise ValueError(f"unknown tone-mapping operator {operator!r}; known: {', '.join(OPERATORS)}") from None
    display = op(np.asarray(linear_rgb, np.float64))
    encoded = colour.models.eotf_inverse_sRGB(display)
    return np.clip(np.round(encoded * 255.0), 0, 255).astype(np.uint8)
