"""Background images the cloth is composited over (the paper used indoor photographs).

``procedural``: a seeded procedural room (``textures.indoor_background``);
``folder``: the user's images in ``variant.background_dir``, optionally split 80/20
by file name into ``train`` and ``heldout`` sets so a test set can use
backgrounds the network never saw; ``none`` and ``room`` (geometry rendered in
the scene instead) composite over black.

A file that cannot be read is reported by name (a warning) and skipped, and the
draw moves on to another image: one bad download must not stop a long run.
"""

from __future__ import annotations

import os
import warnings
import zlib
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError
from skimage.transform import resize

from render.exr import read_exr
from render.textures import indoor_background, srgb_to_linear
from render.variants import RenderVariant

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".exr")
HELDOUT_MODULUS = 5  # one file in five (by a hash of its name) is held out


class BackgroundError(RuntimeError):
    """No usable background image; the message names the folder."""


def background_split(name: str) -> str:
    """'heldout' or 'train' for a file name: stable across machines, runs and folder contents."""
    return "heldout" if zlib.crc32(name.encode("utf-8")) % HELDOUT_MODULUS == 0 else "train"


class Backgrounds:
    """Draws one background per clip for a variant, at the render resolution."""

    def __init__(self, variant: RenderVariant, size: int):
        self.variant = variant
        self.size = size
        self.skipped: dict[str, str] = {}  # unreadable file -> reason, reported once each
        self.files: list[Path] = []
        if variant.background == "folder":
            self.folder = Path(os.path.expandvars(os.path.expanduser(variant.background_dir)))
            if not self.folder.is_dir():
                raise BackgroundError(f"variant {variant.name!r}: background_dir {self.folder} is not a folder")
            files = sorted(p for p in self.folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            if variant.background_split != "all":
                files = [p for p in files if background_split(p.name) == variant.background_split]
            if not files:
                raise BackgroundError(f"variant {variant.name!r}: no {variant.background_split} background images "
                                      f"({', '.join(IMAGE_SUFFIXES)}) in {self.folder}")
            self.files = files

    def draw(self, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
        """(linear RGB (size, size, 3) float32, info for the clip's meta)."""
        kind = self.variant.background
        if kind == "procedural":
            return indoor_background(rng, self.size), {"kind": kind}
        if kind in ("none", "room"):
            return np.zeros((self.size, self.size, 3), np.float32), {"kind": kind}
        order = rng.permutation(len(self.files))
        for index in order:
            path = self.files[index]
            if str(path) in self.skipped:
                continue
            try:
                image = _load_image(path)
            except (OSError, ValueError, UnidentifiedImageError) as e:
                self.skipped[str(path)] = str(e)
                warnings.warn(f"background image {path} cannot be read ({e}); skipping it", stacklevel=2)
                continue
            return self._square(image, rng), {"kind": kind, "file": str(path.relative_to(self.folder))}
        raise BackgroundError(f"none of the {len(self.files)} background images in {self.folder} can be read "
                              f"(see the warnings above)")

    def _square(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A random square crop of the image, resized to the render size."""
        h, w = image.shape[:2]
        side = min(h, w)
        y0 = int(rng.integers(0, h - side + 1))
        x0 = int(rng.integers(0, w - side + 1))
        crop = image[y0:y0 + side, x0:x0 + side]
        return resize(crop, (self.size, self.size), anti_aliasing=side > self.size).astype(np.float32)


def _load_image(path: Path) -> np.ndarray:
    """Linear RGB float32 from an 8/16-bit sRGB image or a linear EXR."""
    if path.suffix.lower() == ".exr":
        return np.asarray(read_exr(path)[..., :3], np.float32)
    with Image.open(path) as im:
        im.load()
        rgb = np.asarray(im.convert("RGB"), np.float32) / 255.0
    if rgb.ndim != 3 or min(rgb.shape[:2]) < 1:
        raise ValueError(f"unexpected image shape {rgb.shape}")
    return srgb_to_linear(rgb)
