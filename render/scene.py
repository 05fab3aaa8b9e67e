"""One Mitsuba scene per clip: build it once, move the cloth in place every frame.

``ClipRenderer(clip, variant, ...)`` draws everything random about the clip
(texture, background, lights, camera errors) from named seed streams, frames a
camera on the clip's bounding box over all frames, and builds the scene with
the cloth as an in-memory ``mi.Mesh``. ``render_frame(t)`` writes frame t's
vertex positions into that mesh (``mi.traverse`` + ``params.update()``; Mitsuba
recomputes normals and the BVH) and renders; the scene is rebuilt only when the
vertex or face count changes (adaptive remeshing). Rebuilding per frame would
leak memory and, on the JIT backends, cost far more than the render itself.

A frame comes back twice: the cloth's linear RGBA radiance (what goes to EXR,
alpha = coverage, the background not in it) and the 8-bit sRGB image the
network reads: cloth composited over the background under its alpha in linear
light, passed through the camera effects and the variant's tone-mapping operator.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

import numpy as np

from clothgap import seeding
from render.backend import load_mitsuba
from render.backgrounds import Backgrounds
from render.camera import apply_camera, draw_camera
from render.lighting import Framing, emitters, room_shapes
from render.materials import cloth_bsdf
from render.textures import make_texture
from render.tonemap import tonemap
from render.variants import RenderVariant
from sim.clip import SimClip

FOV_DEG = 40.0
ELEVATION_DEG = 12.0   # the camera looks slightly down on the cloth, as a person filming it would
FRAME_MARGIN = 1.3     # the clip's bounding box fills 1/1.3 of the frame: background shows around it

# Named seed streams (clothgap.seeding): one per randomizer, never renamed.
STREAMS = ("texture", "background", "lighting", "room", "camera", "noise", "sampler")


@dataclass
class Frame:
    hdr: np.ndarray  # (H, W, 4) float32: linear cloth radiance + alpha
    ldr: np.ndarray  # (H, W, 3) uint8: sRGB, composited, tone-mapped


def frame_camera(lo: np.ndarray, hi: np.ndarray, fov_deg: float = FOV_DEG) -> Framing:
    """A camera that sees the whole box [lo, hi] (z up) from the side where the box is thinnest.

    Cloth hangs roughly in a vertical plane, so looking along the thinner
    horizontal axis sees its face rather than its edge.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    center, extent = (lo + hi) / 2, hi - lo
    axis = 1 if extent[1] <= extent[0] else 0
    view = np.zeros(3)
    view[axis] = -1.0
    elevation = np.radians(ELEVATION_DEG)
    direction = np.cos(elevation) * view + np.sin(elevation) * np.array([0.0, 0.0, 1.0])
    across = max(extent[1 - axis], extent[2], 1e-3)
    distance = FRAME_MARGIN * (across / 2) / np.tan(np.radians(fov_deg) / 2) + extent[axis] / 2
    radius = float(np.linalg.norm(extent) / 2)
    return Framing(target=center, origin=center + distance * direction, distance=float(distance),
                   radius=max(radius, 1e-3), fov_deg=fov_deg, floor_z=float(lo[2]))


class ClipRenderer:
    """Renders the frames of one clip under one variant (one scene, updated in place)."""

    def __init__(self, clip: SimClip, variant: RenderVariant, *, resolution: int, spp: int, run_seed: int,
                 clip_index: int, backend: str = "auto", backgrounds: Backgrounds | None = None):
        self.mi: ModuleType = load_mitsuba(backend)
        self.clip, self.variant = clip, variant
        self.resolution, self.spp = int(resolution), int(spp)
        self.sampler_seed = seeding.derive_int(run_seed, clip_index, seeding.RENDER, "sampler")

        def stream(*name: str | int) -> np.random.Generator:
            return seeding.rng(run_seed, clip_index, seeding.RENDER, *name)

        self.texture = make_texture(variant.texture, stream("texture"), variant.texture_tile_m)
        backgrounds = backgrounds or Backgrounds(variant, self.resolution)
        self.background, background_info = backgrounds.draw(stream("background"))
        self.framing = frame_camera(*clip.bounds())
        self.lights, lighting_info = emitters(self.mi, variant, self.framing, stream("lighting"))
        self.room = room_shapes(self.mi, variant, self.framing, stream("room"))
        self.camera = draw_camera(variant, stream("camera"))
        self._stream = stream
        self.info = {
            "backend": self.mi.variant(),
            "run_seed": int(run_seed),
            "clip_index": int(clip_index),
            "seed_streams": list(STREAMS),  # clothgap.seeding.rng(run_seed, clip_index, RENDER, stream[, frame])
            "sampler_seed": self.sampler_seed,
            "draws": {  # what the seeded randomizers picked for this clip
                "texture": self.texture.info(),
                "background": background_info,
                "lighting": lighting_info,
                "camera": {**self.camera.info(), "origin": self.framing.origin.tolist(),
                           "target": self.framing.target.tolist(), "fov_deg": self.framing.fov_deg},
            },
        }
        self._bsdf = cloth_bsdf(self.mi, variant, self.texture)
        self._counts: tuple[int, int] | None = None
        self.scene = None
        self.params = None
        self.rebuilds = 0

    # ---------------------------------------------------------------- scene

    def _build(self, positions: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> None:
        mi = self.mi
        props = mi.Properties()
        props["bsdf"] = self._bsdf
        mesh = mi.Mesh("cloth", len(positions), len(faces), props=props,
                       has_vertex_normals=True, has_vertex_texcoords=True)
        mesh_params = mi.traverse(mesh)
        self._assign(mesh_params, "", positions, faces, uv)
        mesh_params.update()
        res = self.resolution
        scene = {
            "type": "scene",
            # hide_emitters: camera rays that miss the cloth return 0 with alpha 0, so alpha is coverage.
            "integrator": {"type": "path", "max_depth": self.variant.max_depth, "hide_emitters": True},
            "sensor": {
                "type": "perspective", "fov": self.framing.fov_deg,
                "to_world": mi.ScalarTransform4f().look_at(origin=self.framing.origin.tolist(),
                                                           target=self.framing.target.tolist(), up=[0, 0, 1]),
                # A box filter gives each sample to exactly one pixel, as a sensor pixel integrates its own
                # area; wider filters let neighbouring blocks/threads add to a pixel in a varying order,
                # which made repeated renders differ in the last bit.
                "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgba",
                         "component_format": "float32", "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": self.spp},
            },
            "cloth": mesh,
            **self.lights,
            **self.room,
        }
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        self._counts = (len(positions), len(faces))
        self.rebuilds += 1

    def _assign(self, params, prefix: str, positions, faces, uv) -> None:
        """Write one frame's geometry into a mesh's parameters (type(...)(...) works in scalar and JIT variants)."""
        def put(key, array):
            params[prefix + key] = type(params[prefix + key])(np.ascontiguousarray(array).ravel())

        put("vertex_positions", np.asarray(positions, np.float32))
        if faces is not None:
            put("faces", np.asarray(faces, np.uint32))
            put("vertex_texcoords", np.asarray(uv, np.float32) / np.float32(self.texture.tile_m))

    def _set_geometry(self, t: float) -> None:
        positions, faces, uv = self._geometry(t)
        if self._counts != (len(positions), len(faces)):
            self._build(positions, faces, uv)
            return
        # Same counts: move the vertices (and, for remeshed clips, replace faces and uv) in place.
        self._assign(self.params, "cloth.", positions, None if self.clip.fixed_topology else faces, uv)
        self.params.update()

    def _geometry(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geometry at (fractional) time t; between frames of equal topology, vertices are interpolated."""
        t0 = int(np.floor(t))
        positions, faces, uv = self.clip.frame(t0)
        frac = t - t0
        if frac > 0 and t0 + 1 < self.clip.num_frames:
            p1, f1, _ = self.clip.frame(t0 + 1)
            if f1.shape == faces.shape and np.array_equal(f1, faces):
                positions = (1 - frac) * positions + frac * p1
        return positions, faces, uv

    # ---------------------------------------------------------------- frames

    def render_hdr(self, t: int) -> np.ndarray:
        """Frame t's linear cloth RGBA (H, W, 4) float32; with motion blur, the average over the frame interval."""
        n = self.variant.motion_blur_subframes
        spp = max(1, self.spp // n)
        total = np.zeros((self.resolution, self.resolution, 4), np.float64)
        for k in range(n):
            self._set_geometry(t + k / n)
            seed = (self.sampler_seed + t * n + k) & 0xFFFFFFFF
            total += np.asarray(self.mi.render(self.scene, spp=spp, seed=seed), np.float64)
        return (total / n).astype(np.float32)

    def finish(self, hdr: np.ndarray, t: int) -> np.ndarray:
        """Frame t's 8-bit sRGB image the network reads, from the cloth's linear RGBA."""
        rgb, alpha = hdr[..., :3], hdr[..., 3:4]
        composite = rgb + (1.0 - np.clip(alpha, 0.0, 1.0)) * self.background  # rgb is premultiplied by coverage
        recorded = apply_camera(composite, self.variant, self.camera, self._stream("noise", t))
        return tonemap(recorded, self.variant.tonemap)

    def render_frame(self, t: int) -> Frame:
        hdr = self.render_hdr(t)
        return Frame(hdr=hdr, ldr=self.finish(hdr, t))
