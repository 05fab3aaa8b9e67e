"""A simulated clip's frames as mesh files (PLY, OBJ, glTF binary) through trimesh, for Blender or MeshLab.

One file per frame, ``<clip_id>_<frame:04d>.<format>``, each the frame's own vertices, triangles and
texture coordinates (the material coordinates in metres, as the renderer tiles its textures), so adaptive
clips, whose topology changes between frames, export the same way. Positions are the simulated ones in
metres. PLY and OBJ keep the simulation's axes (z up); GLB is turned to glTF's +Y up, as the format
requires, by (x, y, z) -> (x, z, -y), so the cloth hangs upright in any glTF viewer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clothgap.errors import ConfigError, InputError
from clothgap.files import atomic_path
from sim.clip import SimClip

FORMATS = ("ply", "obj", "glb")
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])   # (x, y, z) -> (x, z, -y) = M @ p


def parse_frames(spec: str | None, num_frames: int) -> list[int]:
    """Frame numbers from ``"0,5,10-19"`` (ranges inclusive; None or ``"all"``: every frame), sorted, once each."""
    if spec is None or spec.strip().lower() == "all":
        return list(range(num_frames))
    out: set[int] = set()
    for part in filter(None, (p.strip() for p in spec.split(","))):
        lo, dash, hi = part.partition("-")
        try:
            first, last = int(lo), int(hi) if dash else int(lo)
        except ValueError:
            raise ConfigError(f"--frames {spec!r}: {part!r} is not a frame number or a range like 10-19") from None
        if not 0 <= first <= last < num_frames:
            raise ConfigError(f"--frames {spec!r}: {part!r} is outside the clip's frames 0..{num_frames - 1}")
        out.update(range(first, last + 1))
    if not out:
        raise ConfigError(f"--frames {spec!r} names no frame")
    return sorted(out)


def frame_mesh(clip: SimClip, t: int, fmt: str = "ply"):
    """Frame ``t`` of ``clip`` as a ``trimesh.Trimesh`` in the axes of ``fmt`` (vertex order kept)."""
    import trimesh

    positions, faces, uv = clip.frame(t)
    vertices = np.asarray(positions, np.float64)
    if fmt == "glb":
        vertices = vertices @ Z_UP_TO_Y_UP.T
    return trimesh.Trimesh(vertices, np.asarray(faces, np.int64), process=False,
                           visual=trimesh.visual.TextureVisuals(uv=np.asarray(uv, np.float64)))


def export_clip(clip_dir: Path | str, out: Path | str, fmt: str = "ply", frames: str | None = None) -> list[Path]:
    """Write the chosen frames of the finished sim clip in ``clip_dir`` as ``fmt`` files into ``out``.

    Each file appears whole (written beside, then renamed), so a killed export leaves no partial mesh.
    Returns the files written, in frame order.
    """
    if fmt not in FORMATS:
        raise ConfigError(f"unknown mesh format {fmt!r}; known: {', '.join(FORMATS)}")
    clip_dir, out = Path(clip_dir), Path(out)
    try:
        clip = SimClip.load(clip_dir)
    except (OSError, ValueError, KeyError) as e:
        raise InputError(f"{clip_dir} does not hold a readable sim clip ({e})") from None
    chosen = parse_frames(frames, clip.num_frames)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for t in chosen:
        data = frame_mesh(clip, t, fmt).export(file_type=fmt)
        path = out / f"{clip_dir.name}_{t:04d}.{fmt}"
        with atomic_path(path) as tmp:
            tmp.write_bytes(data.encode() if isinstance(data, str) else data)
        written.append(path)
    return written
