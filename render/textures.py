"""Procedural cloth textures and indoor background images, drawn from a seeded generator.

Cloth textures are square tiles that repeat seamlessly (every pattern is periodic
on the tile) and are mapped through the simulator's uv, which is in metres: a
tile spans ``tile_m`` metres of cloth. All images are returned as *linear* RGB
float32 (the renderer's working space); they are designed in sRGB, like the
photos and prints they imitate, and converted once here.

Every tile has the same pixel size, so each clip's scene compiles to the same
kernels and Dr.Jit's cache is reused from clip to clip.
"""

from __future__ import annotations

from dataclasses import dataclass

import colour
import numpy as np
from skimage.color import hsv2rgb
from skimage.transform import resize

TEXTURE_SIZE = 128  # pixels per tile side
PATTERNS = ("stripes", "plaid", "dots", "noise", "weave")

GRID_TILE_M = 0.2       # the grid texture: one tile = 20 cm of cloth ...
GRID_LINES = 8          # ... with 8 lines each way: 2.5 cm squares


@dataclass(frozen=True)
class ClothTexture:
    image: np.ndarray   # (TEXTURE_SIZE, TEXTURE_SIZE, 3) linear RGB float32
    tile_m: float       # metres of cloth one tile spans
    pattern: str        # what was drawn ("grid", "color", or one of PATTERNS)

    def info(self) -> dict:
        return {"pattern": self.pattern, "tile_m": self.tile_m}


_SRGB_LINEAR_KNEE = float(colour.models.eotf_inverse_sRGB(0.0031308))


def srgb_to_linear(image: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] -> linear float32: colour-science's ``eotf_sRGB`` written out (the same float64 steps)."""
    v = np.clip(np.asarray(image, np.float64), 0.0, 1.0)
    return np.where(v <= _SRGB_LINEAR_KNEE, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def make_texture(family: str, rng: np.random.Generator, tile_range: tuple[float, float]) -> ClothTexture:
    """A cloth texture of ``family`` ("random", "grid" or "color"); ``tile_range`` bounds the tile size in metres."""
    n = TEXTURE_SIZE
    if family == "grid":
        return ClothTexture(srgb_to_linear(_grid(n)), GRID_TILE_M, "grid")
    if family == "color":
        color = palette(rng, 1)[0]
        return ClothTexture(srgb_to_linear(np.broadcast_to(color, (n, n, 3))), float(tile_range[1]), "color")
    if family == "random":
        pattern = str(rng.choice(PATTERNS))
        tile_m = float(rng.uniform(*tile_range))
        image = {"stripes": _stripes, "plaid": _plaid, "dots": _dots, "noise": _noise, "weave": _weave}[pattern](rng, n)
        return ClothTexture(srgb_to_linear(image), tile_m, pattern)
    raise ValueError(f"unknown texture family {family!r}; known: random, grid, color")


# ---------------------------------------------------------------- palettes and coordinates

def palette(rng: np.random.Generator, k: int) -> np.ndarray:
    """``k`` sRGB colours that go together: a base hue plus analogous or complementary ones."""
    base = rng.uniform()
    spread = rng.choice([0.05, 0.1, 0.5])  # analogous, wider, complementary
    hues = (base + spread * np.arange(k) + rng.normal(0, 0.02, k)) % 1.0
    sats = rng.uniform(0.15, 0.85, k)
    vals = rng.uniform(0.25, 0.95, k)
    return hsv2rgb(np.stack([hues, sats, vals], -1)[None])[0].astype(np.float32)


def _uv(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates in [0, 1) on the tile (periodic functions of these tile seamlessly)."""
    c = (np.arange(n) + 0.5) / n
    return np.meshgrid(c, c, indexing="xy")


def _band(x: np.ndarray, count: int, width: float) -> np.ndarray:
    """1 on ``count`` evenly spaced bands of relative ``width`` along x in [0, 1), else 0 (soft edges)."""
    phase = (x * count) % 1.0
    edge = 0.5 / (TEXTURE_SIZE / max(count, 1))  # about half a pixel, to anti-alias
    return np.clip((width / 2 - np.abs(phase - 0.5)) / edge + 0.5, 0.0, 1.0)


# ---------------------------------------------------------------- patterns (sRGB, periodic on the tile)

def _grid(n: int) -> np.ndarray:
    u, v = _uv(n)
    lines = np.maximum(_band(u, GRID_LINES, 0.12), _band(v, GRID_LINES, 0.12))[..., None]
    light, dark = np.array([0.9, 0.9, 0.88]), np.array([0.08, 0.08, 0.1])
    return light * (1 - lines) + dark * lines


def _stripes(rng: np.random.Generator, n: int) -> np.ndarray:
    u, v = _uv(n)
    colors = palette(rng, int(rng.integers(2, 4)))
    direction = rng.choice(["u", "v", "diagonal"])
    x = {"u": u, "v": v, "diagonal": (u + v) % 1.0}[direction]
    count = int(rng.integers(2, 9))
    index = np.floor((x * count * len(colors)) % len(colors)).astype(int)
    return colors[index]


def _plaid(rng: np.random.Generator, n: int) -> np.ndarray:
    u, v = _uv(n)
    base, a, b = palette(rng, 3)
    count = int(rng.integers(1, 5))
    wa, wb = rng.uniform(0.15, 0.5, 2)
    ma, mb = _band(u, count, wa)[..., None], _band(v, count, wb)[..., None]
    image = base * (1 - ma) + a * ma
    image = image * (1 - 0.6 * mb) + b * 0.6 * mb  # crossing bands mix, as dyed threads do
    thin = np.maximum(_band(u, 2 * count, 0.04), _band(v, 2 * count, 0.04))[..., None]
    return image * (1 - thin) + rng.uniform(0, 1) * thin


def _dots(rng: np.random.Generator, n: int) -> np.ndarray:
    u, v = _uv(n)
    background, dot = palette(rng, 2)
    count = 2 * int(rng.integers(1, 5))  # even, so staggered rows still tile
    radius = rng.uniform(0.15, 0.4)
    stagger = rng.integers(0, 2)  # 1: every other row shifted half a cell
    cu = (u * count + stagger * 0.5 * (np.floor(v * count) % 2)) % 1.0
    cv = (v * count) % 1.0
    dist = np.hypot(cu - 0.5, cv - 0.5)
    edge = count / n
    mask = np.clip((radius - dist) / edge + 0.5, 0, 1)[..., None]
    return background * (1 - mask) + dot * mask


def _noise(rng: np.random.Generator, n: int) -> np.ndarray:
    # Periodic smooth noise: white noise low-passed in the Fourier domain (FFT filtering wraps around).
    freq = np.fft.fftfreq(n)[:, None] ** 2 + np.fft.fftfreq(n)[None, :] ** 2
    cutoff = rng.uniform(0.01, 0.08)
    field = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-freq / (2 * cutoff ** 2))))
    field = (field - field.min()) / (np.ptp(field) + 1e-12)
    colors = palette(rng, 3)
    t = field[..., None] * 2
    return np.where(t < 1, colors[0] * (1 - t) + colors[1] * t, colors[1] * (2 - t) + colors[2] * (t - 1))


def _weave(rng: np.random.Generator, n: int) -> np.ndarray:
    """Warp and weft threads going over and under each other (plain or twill weave), shaded across each thread."""
    u, v = _uv(n)
    warp, weft = palette(rng, 2)
    threads = int(rng.choice([6, 12, 24]))  # divisible by 2 and 3, so both weaves tile
    repeat = int(rng.choice([2, 3]))  # 2: plain weave (checker), 3: twill (diagonal ribs)
    iu, iv = np.floor(u * threads).astype(int), np.floor(v * threads).astype(int)
    warp_on_top = (iu + iv) % repeat != 0
    fu, fv = (u * threads) % 1.0, (v * threads) % 1.0
    shade_warp = 0.55 + 0.45 * np.sin(np.pi * fu)  # a thread is brightest along its middle
    shade_weft = 0.55 + 0.45 * np.sin(np.pi * fv)
    image = np.where(warp_on_top[..., None], warp * shade_warp[..., None], weft * shade_weft[..., None])
    return np.clip(image, 0, 1)


# ---------------------------------------------------------------- procedural indoor background

def indoor_background(rng: np.random.Generator, size: int) -> np.ndarray:
    """A simple procedural room (wall, floor, window, furniture, a picture) as linear RGB (size, size, 3).

    Stands in for the paper's indoor photographs (SUN-style scenes) when no image
    folder is given: it has the clutter and edges the network must learn to ignore.
    """
    s = 2 * size  # draw at twice the size, then downsample (anti-aliasing)
    # Pixel coordinates in [0, 1): y down the rows, x across the columns. The room's regions are row and
    # column ranges of them, so they are drawn as slices (a mask over the whole image costs 10x more).
    coord = np.arange(s) / s
    x, y = coord[None, :], coord[:, None]

    def first(at_least: float) -> int:
        """The first pixel whose coordinate is >= ``at_least``."""
        return int(np.searchsorted(coord, at_least, side="left"))

    wall, floor, furniture, accent = palette(rng, 4)
    wall = 0.5 * wall + 0.4  # walls are light and muted
    horizon = rng.uniform(0.55, 0.8)
    image = np.empty((s, s, 3))
    image[:] = wall * (0.8 + 0.25 * (1 - y))[..., None]  # light falls off from the ceiling
    f0 = int(np.count_nonzero(coord <= horizon))        # the floor: rows below the horizon
    floor_y = y[f0:]
    image[f0:] = (floor * 0.7) * (0.8 + 0.3 * (floor_y - horizon))[..., None]
    planks = int(rng.integers(4, 12))
    seams = _band(((x - 0.5) / np.maximum(floor_y - horizon + 0.3, 1e-3)) % 1.0, planks, 0.04)
    image[f0:] *= (1 - 0.3 * seams)[..., None]

    def rect(x0, y0, w, h, color):
        image[first(y0):first(y0 + h), first(x0):first(x0 + w)] = color

    # A window: a bright sky with a frame and a cross bar.
    wx, wy, ww, wh = rng.uniform(0.05, 0.6), rng.uniform(0.08, 0.2), rng.uniform(0.2, 0.35), rng.uniform(0.2, 0.3)
    rect(wx - 0.015, wy - 0.015, ww + 0.03, wh + 0.03, np.array([0.92, 0.92, 0.9]))
    rect(wx, wy, ww, wh, np.array([0.75, 0.85, 1.0]) * rng.uniform(0.85, 1.0))
    rect(wx + ww / 2 - 0.007, wy, 0.014, wh, np.array([0.92, 0.92, 0.9]))
    # Furniture standing on the floor, and a picture on the wall.
    for _ in range(int(rng.integers(1, 4))):
        fw, fh = rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.4)
        fx = rng.uniform(-0.1, 0.9)
        color = furniture * rng.uniform(0.5, 1.0)
        rect(fx, horizon + rng.uniform(0.0, 0.1) - fh, fw, fh, color)
        rect(fx, horizon + rng.uniform(0.0, 0.1) - fh, fw, 0.02, color * 1.2)
    px, py = rng.uniform(0.1, 0.8), rng.uniform(0.15, 0.35)
    rect(px, py, 0.12, 0.09, accent * 0.4)
    rect(px + 0.01, py + 0.01, 0.1, 0.07, accent)
    image += rng.normal(0, 0.015, image.shape)  # sensor-like grain, so flat walls are not perfectly flat
    image = resize(np.clip(image, 0, 1), (size, size), anti_aliasing=True)
    return srgb_to_linear(image)
