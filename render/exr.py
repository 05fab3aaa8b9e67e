"""Linear HDR frames as OpenEXR files, through the OpenEXR package (exact round trips).

Frames are RGBA: the cloth's radiance (linear, unclipped, so values above 1
survive) and its coverage alpha. ``half=True`` stores 16-bit floats (half the
disk, 3 significant digits); reading returns exactly what was written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

from clothgap.files import atomic_path

_HEADER = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}


def write_exr(path: Path, rgba: np.ndarray, half: bool = False) -> None:
    """Write an (H, W, 4) linear RGBA image as float32 (or half) EXR."""
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise ValueError(f"write_exr({path}): expected an (H, W, 4) RGBA array, got shape {rgba.shape}")
    pixels = np.ascontiguousarray(rgba, np.float16 if half else np.float32)
    with atomic_path(path, keep_suffix=True) as tmp, OpenEXR.File(dict(_HEADER), {"RGBA": pixels}) as f:
        f.write(str(tmp))


def read_exr(path: Path) -> np.ndarray:
    """An RGBA (or RGB) EXR as an (H, W, 4) (or (H, W, 3)) array, in the dtype it was stored in."""
    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        for group in ("RGBA", "RGB"):
            if group in channels:
                return np.array(channels[group].pixels)
        raise ValueError(f"{path}: expected RGBA or RGB channels, found {', '.join(channels)}")
