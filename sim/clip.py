"""SimClip: one simulated sequence on disk, the contract between sim and render.

A clip folder holds ``clip.npz`` (geometry) and ``meta.json`` (labels, seeds,
material coefficients, motion parameters), then ``DONE``. Geometry is stored
per frame with offsets, so meshes whose topology changes between frames
(adaptive remeshing) use the same format as fixed meshes:

    positions  (sum_t V_t, 3) float32   world positions, metres, z up
    uv         (sum_t V_t, 2) float32   material coordinates, metres
    faces      (sum_t F_t, 3) int32     indices into the frame's own vertices
    vertex_offsets, face_offsets  (T + 1,) int64

A fixed-topology clip stores ``faces`` and ``uv`` once (``fixed_topology``),
which keeps paper-scale datasets small.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np


@dataclass
class SimClip:
    meta: dict
    positions: np.ndarray
    uv: np.ndarray
    faces: np.ndarray
    vertex_offsets: np.ndarray
    face_offsets: np.ndarray
    fixed_topology: bool = field(default=False)

    # ---- construction
    @classmethod
    def from_frames(cls, meta: dict, frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> "SimClip":
        """``frames``: (positions (V,3), faces (F,3), uv (V,2)) per frame."""
        if not frames:
            raise ValueError("a clip needs at least one frame")
        fixed = all(f[1].shape == frames[0][1].shape and np.array_equal(f[1], frames[0][1]) for f in frames)
        pos = np.concatenate([np.asarray(f[0], np.float32) for f in frames])
        vo = np.cumsum([0] + [len(f[0]) for f in frames]).astype(np.int64)
        if fixed:
            faces = np.asarray(frames[0][1], np.int32)
            uv = np.asarray(frames[0][2], np.float32)
            fo = np.array([0, len(faces)], np.int64)
        else:
            faces = np.concatenate([np.asarray(f[1], np.int32) for f in frames])
            uv = np.concatenate([np.asarray(f[2], np.float32) for f in frames])
            fo = np.cumsum([0] + [len(f[1]) for f in frames]).astype(np.int64)
        return cls(dict(meta), pos, uv, faces, vo, fo, fixed)

    @classmethod
    def from_fixed(cls, meta: dict, positions: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> "SimClip":
        """A clip whose topology never changes: positions (T, V, 3)."""
        t, v, _ = positions.shape
        return cls(dict(meta), np.asarray(positions, np.float32).reshape(t * v, 3),
                   np.asarray(uv, np.float32), np.asarray(faces, np.int32),
                   np.arange(t + 1, dtype=np.int64) * v, np.array([0, len(faces)], np.int64), True)

    # ---- access
    @property
    def num_frames(self) -> int:
        return len(self.vertex_offsets) - 1

    def frame(self, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(positions (V,3), faces (F,3), uv (V,2)) of frame ``t``."""
        if not 0 <= t < self.num_frames:
            raise IndexError(f"frame {t} out of range 0..{self.num_frames - 1}")
        v0, v1 = self.vertex_offsets[t], self.vertex_offsets[t + 1]
        if self.fixed_topology:
            return self.positions[v0:v1], self.faces, self.uv
        f0, f1 = self.face_offsets[t], self.face_offsets[t + 1]
        return self.positions[v0:v1], self.faces[f0:f1], self.uv[v0:v1]

    def frames(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        for t in range(self.num_frames):
            yield self.frame(t)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds over the whole sequence (for framing a camera)."""
        return self.positions.min(axis=0), self.positions.max(axis=0)

    # ---- disk
    def save(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        # Uncompressed: float32 positions of a moving cloth shrink only ~17 % under zlib, which took ~10x
        # the write time (benchmarks/results/sim_write-wind-uniform1-200.json).
        np.savez(folder / "clip.npz", positions=self.positions, uv=self.uv, faces=self.faces,
                 vertex_offsets=self.vertex_offsets, face_offsets=self.face_offsets,
                 fixed_topology=np.array(self.fixed_topology))
        (folder / "meta.json").write_text(json.dumps(self.meta, indent=2, default=_py) + "\n")

    @classmethod
    def load(cls, folder: Path) -> "SimClip":
        folder = Path(folder)
        with np.load(folder / "clip.npz") as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads((folder / "meta.json").read_text())
        return cls(meta, arrays["positions"], arrays["uv"], arrays["faces"], arrays["vertex_offsets"],
                   arrays["face_offsets"], bool(arrays["fixed_topology"]))


def _py(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
