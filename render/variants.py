"""Render variants: named, frozen sets of rendering choices, one TOML file each.

A variant is what the study compares: ``paper`` reproduces the paper's renders
(random procedural texture, diffuse cloth with sheen, fixed lighting, composited
over a procedural indoor background, plain sRGB tone mapping), and every other
variant changes one or a few axes of it. The dataclass defaults *are* the paper
setting, so a variant file lists only what it changes::

    # assets/render_variants/reinhard.toml
    description = "The paper's setting, tone-mapped with Reinhard instead of clipping."
    tonemap = "reinhard"

A file may also name ``base = "<variant>"`` to start from another variant
instead of ``paper``. Variants are read from ``assets/render_variants/*.toml``
and from the folder in ``$CLOTHGAP_VARIANTS_DIR`` (the user's own); a user adds
one by dropping a file there. Two files of the same name are an error, so a
variant name always means one thing.
"""

from __future__ import annotations

import dataclasses
import os
import re
import tomllib
import typing
from dataclasses import dataclass
from pathlib import Path

from clothgap.errors import UserError

VARIANTS_DIR = Path(__file__).resolve().parent.parent / "assets" / "render_variants"
USER_VARIANTS_ENV = "CLOTHGAP_VARIANTS_DIR"
VARIANT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")
PAPER = "paper"

# Allowed values of the enumerated settings (the renderer dispatches on these).
CHOICES: dict[str, tuple[str, ...]] = {
    "texture": ("random", "grid", "color"),
    "bsdf": ("principled", "diffuse", "principledthin", "tabulated", "measured"),
    "lighting": ("fixed", "random", "daylight"),
    "background": ("procedural", "none", "folder", "room"),
    "background_split": ("all", "train", "heldout"),
    "tonemap": ("srgb_clip", "reinhard", "filmic"),
}


class VariantError(UserError, ValueError):
    """A variant name or file is wrong; the message names the file or the known variants."""


@dataclass(frozen=True)
class RenderVariant:
    """Everything that decides how a clip looks, apart from resolution and spp (those are in RenderConfig)."""

    name: str = PAPER
    description: str = ""
    # Cloth appearance
    texture: str = "random"                 # "random" (procedural patterns), "grid", "color" (one solid colour)
    texture_tile_m: tuple[float, ...] = (0.08, 0.3)  # metres one texture tile spans: (min, max), drawn per clip
    bsdf: str = "principled"                # "principled" (diffuse-like with sheen), "diffuse", "principledthin",
                                            # "tabulated" (render.fabric_bsdf), "measured"
    roughness: float = 0.85
    sheen: float = 0.6                      # principled sheen weight (cloth's grazing-angle fuzz)
    diffuse_transmission: float = 0.3       # principledthin only: light passing through thin fabric
    tabulated_file: str = ""                # bsdf="tabulated": a table .npz (empty: the shipped Charlie-sheen table)
    measured_file: str = ""                 # bsdf="measured": an RGL .bsdf file (its own colour; the texture is unused)
    # Lighting and surroundings
    lighting: str = "fixed"                 # "fixed" (key + fill + ambient), "random" (per clip), "daylight"
    background: str = "procedural"          # "procedural" indoor image, "none" (black), "folder" images, "room" geometry
    background_dir: str = ""                # background="folder": images (png/jpg/exr) to draw from
    background_split: str = "all"           # "train" / "heldout": a fixed 80/20 split of background_dir by file name
    # Camera and image pipeline
    tonemap: str = "srgb_clip"              # "srgb_clip", "reinhard", "filmic"
    exposure_stops: float = 0.0             # fixed exposure compensation
    exposure_jitter_stops: float = 0.0      # per-clip exposure error, uniform +- this many stops
    white_balance_jitter: float = 0.0       # per-clip RGB gain error, uniform +- this fraction
    shot_noise: float = 0.0                 # Poisson-like noise: variance = shot_noise * signal
    read_noise: float = 0.0                 # Gaussian read noise, standard deviation in linear units
    vignetting: float = 0.0                 # fraction of light lost at the image corners
    motion_blur_subframes: int = 1          # >1: average this many renders across the frame interval
    video_crf: int = 0                      # >0: encode and decode each clip with H.264 at this CRF (PyAV)
    max_depth: int = 4                      # path length (light bounces + 1)
    zoom: float = 1.0                       # the camera's field of view narrowed by this factor from where it
                                            # stands (>1: the cloth fills more of the frame; the lights and room
                                            # stay where they were; a cloth that moves far may leave the frame),
                                            # times the clip's own view_zoom (sim.arm_view_zoom for arm clips)

    def __post_init__(self) -> None:
        for key, allowed in CHOICES.items():
            value = getattr(self, key)
            if value not in allowed:
                raise VariantError(f"variant {self.name!r}: {key}={value!r} is not one of {', '.join(allowed)}")
        if len(self.texture_tile_m) != 2 or not 0 < self.texture_tile_m[0] <= self.texture_tile_m[1]:
            raise VariantError(f"variant {self.name!r}: texture_tile_m must be [min, max] metres, "
                               f"got {list(self.texture_tile_m)}")
        if self.background == "folder" and not self.background_dir:
            raise VariantError(f"variant {self.name!r}: background='folder' needs background_dir")
        if self.bsdf == "measured" and not self.measured_file:
            raise VariantError(f"variant {self.name!r}: bsdf='measured' needs measured_file (an RGL .bsdf file)")
        if not self.zoom > 0:
            raise VariantError(f"variant {self.name!r}: zoom must be positive, got {self.zoom}")
        if self.motion_blur_subframes < 1 or self.max_depth < 1 or self.video_crf < 0:
            raise VariantError(f"variant {self.name!r}: motion_blur_subframes and max_depth must be >= 1, "
                               "video_crf >= 0")

    def settings(self) -> dict:
        """The rendering settings (everything but name and description), JSON-ready."""
        data = dataclasses.asdict(self)
        del data["name"], data["description"]
        data["texture_tile_m"] = list(self.texture_tile_m)
        return data

    def changes_from(self, other: "RenderVariant") -> dict:
        """The settings whose value differs from ``other`` (e.g. from ``paper``)."""
        mine, theirs = self.settings(), other.settings()
        return {k: v for k, v in mine.items() if v != theirs[k]}


_FIELDS = {f.name: f for f in dataclasses.fields(RenderVariant)}
_HINTS = typing.get_type_hints(RenderVariant)


def _coerce(key: str, value: object, source: Path) -> object:
    tp = _HINTS[key]
    if typing.get_origin(tp) is tuple:
        if not isinstance(value, list):
            raise VariantError(f"{source}: {key} must be a list, got {value!r}")
        return tuple(float(v) for v in value)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
        raise VariantError(f"{source}: {key} must be {tp.__name__}, got {value!r}")
    return value


def _variant_files() -> dict[str, Path]:
    folders = [VARIANTS_DIR]
    user = os.environ.get(USER_VARIANTS_ENV)
    if user:
        if not Path(user).is_dir():
            raise VariantError(f"${USER_VARIANTS_ENV}={user} is not a folder")
        folders.append(Path(user))
    files: dict[str, Path] = {}
    for folder in folders:
        for path in sorted(folder.glob("*.toml")):
            if not VARIANT_NAME.fullmatch(path.stem):
                # The name becomes a folder (render/<variant>/): "...toml" would be "..", outside the run.
                raise VariantError(f"{path}: a variant file's name must be letters, digits, '_' or '-' "
                                   f"(starting with a letter or digit) followed by .toml; rename it")
            if path.stem in files:
                raise VariantError(f"variant {path.stem!r} is defined twice: {files[path.stem]} and {path}; "
                                   "rename one of the files")
            files[path.stem] = path
    return files


def _read(path: Path) -> dict:
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise VariantError(f"{path}: not valid TOML ({e})") from None
    unknown = set(data) - set(_FIELDS) - {"base"} | ({"name"} & set(data))
    if unknown:
        raise VariantError(f"{path}: unknown setting(s) {', '.join(sorted(unknown))}; known: "
                           f"base, {', '.join(k for k in _FIELDS if k != 'name')}")
    if not isinstance(data.get("description"), str) or not data["description"].strip():
        raise VariantError(f"{path}: every variant needs a description (what it changes relative to paper, and why)")
    return data


def _build(name: str, files: dict[str, Path], seen: tuple[str, ...] = ()) -> RenderVariant:
    if name in seen:
        raise VariantError(f"variant bases form a cycle: {' -> '.join(seen + (name,))}")
    if name not in files:
        raise VariantError(f"unknown render variant {name!r}; known variants: {', '.join(sorted(files))}")
    path = files[name]
    data = _read(path)
    base_name = data.pop("base", PAPER if name != PAPER else None)
    base = _build(base_name, files, seen + (name,)) if base_name else RenderVariant()
    kwargs = {k: _coerce(k, v, path) for k, v in data.items()}
    return dataclasses.replace(base, name=name, **kwargs)


def list_variants() -> list[str]:
    """Names of all registered variants (built-in and the user's), sorted, ``paper`` first."""
    names = sorted(_variant_files())
    return sorted(names, key=lambda n: n != PAPER)


def get_variant(name: str) -> RenderVariant:
    """The variant called ``name``; an unknown name is an error listing the known ones."""
    return _build(name, _variant_files())


def describe_variants() -> str:
    """A human-readable list (for ``clothgap render --list-variants``): name, description, changes."""
    paper = get_variant(PAPER)
    lines = []
    for name in list_variants():
        variant = get_variant(name)
        lines.append(f"{name}: {variant.description.strip()}")
        changes = variant.changes_from(paper)
        if name != PAPER:
            lines.append("    changes: " + (", ".join(f"{k}={v}" for k, v in changes.items()) or "(none)"))
    return "\n".join(lines)
