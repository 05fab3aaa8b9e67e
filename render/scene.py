"""A clip's frames from a Mitsuba scene that is never rebuilt per frame.

``ClipRenderer(clip, variant, ...)`` draws everything random about the clip
(texture, background, lights, camera errors) from named seed streams, frames the
camera on the setting's fixed ``view_box`` and ``view_zoom`` from the sim meta (else on
the clip's own bounds: synthetic clips, garments), and renders the cloth as an in-memory
``mi.Mesh``. ``render_frame(t)`` writes frame t's vertex positions into that
mesh (``mi.traverse`` + ``params.update()``; Mitsuba recomputes normals and the
BVH) and renders. Rebuilding per frame would leak memory and, on the JIT
backends, cost far more than the render itself.

Scenes outlive clips (``ScenePool``). Building a Mitsuba scene is cheap, but
on ``cuda_ad_rgb`` every new scene costs a fresh OptiX compile of the path
tracer (about 0.5 s on an H100, against 1.6 ms of GPU time per 224 px, 16 spp
frame), so a clip does not build its own: it takes a pooled scene of the same
structure (variant, field of view, light and room layout, mesh capacity) and retargets it in
place, writing its camera, lights, room and texture in through ``mi.traverse``.
Meshes are allocated for a capacity and padded (unreferenced vertices,
degenerate faces that no ray hits), so clips and remeshed frames of different
sizes share one scene. On CUDA ``mi.render`` runs under ``dr.freeze``: its
kernels are recorded once per scene and replayed with the new parameters, which
removes the per-frame tracing of the integrator (the larger part of a frame's
time at one frame per launch). The render stage empties the pool once a look is
finished (``render.stage.release_look``): kept, a look's scenes and kernels made
every later look's renders slower and the process larger (benchmarks/render_pool_memory.py).
``reuse_scenes=False`` gives a scene per clip,
rebuilt when the vertex or face count changes: the reference the pool is tested
against.

A frame comes back twice: the cloth's linear RGBA radiance (what goes to EXR,
alpha = coverage, the background not in it) and the 8-bit sRGB image the
network reads: cloth composited over the background under its alpha in linear
light, passed through the camera effects and the variant's tone-mapping operator.
``finish`` makes that image on the host from the read-back RGBA;
``render_finished`` makes it on the backend (``render.device_finish``) and reads
back only the uint8 image (and the RGBA when asked), the same bytes.
``device_finish_unsupported`` says when a variant or backend cannot (sensor
noise, scalar_rgb); callers then take the host path.
"""

from __future__ import annotations

import dataclasses
import json
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from clothgap import seeding
from render.backend import load_mitsuba
from render.backgrounds import Backgrounds
from render.camera import adds_noise, apply_camera, draw_camera
from render.device_finish import DeviceFinish, unsupported as device_unsupported
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


def frame_camera(lo: np.ndarray, hi: np.ndarray, fov_deg: float = FOV_DEG, margin: float = FRAME_MARGIN) -> Framing:
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
    distance = margin * (across / 2) / np.tan(np.radians(fov_deg) / 2) + extent[axis] / 2
    radius = float(np.linalg.norm(extent) / 2)
    return Framing(target=center, origin=center + distance * direction, distance=float(distance),
                   radius=max(radius, 1e-3), fov_deg=fov_deg, floor_z=float(lo[2]))


def zoomed(framing: Framing, zoom: float) -> Framing:
    """``framing`` with its field of view narrowed by ``zoom`` (the camera, lights and room stay put)."""
    if zoom == 1.0:
        return framing
    half = np.radians(framing.fov_deg) / 2
    return dataclasses.replace(framing, fov_deg=float(np.degrees(2 * np.arctan(np.tan(half) / zoom))))


# ---------------------------------------------------------------- pooled scenes

MAX_POOLED_SCENES = 8  # distinct scene structures kept alive per process (least recently used dropped)


# One thread: draws stay in clip order (a folder of backgrounds remembers unreadable files).
_BACKGROUND_DRAWS = ThreadPoolExecutor(1, thread_name_prefix="background-draw")


def _bucket(n: int) -> int:
    """Capacity for a mesh part of n elements: the next power of two (at least 64), so similar clips share."""
    return max(64, 1 << (int(n) - 1).bit_length())


@dataclass
class PooledScene:
    scene: object
    params: object
    capacity: tuple[int, int]   # (vertices, faces) the cloth mesh is allocated for
    frozen: object = None       # dr.freeze'd render function, recorded on first use
    owner: object = None        # the ClipRenderer currently targeting the scene


class ScenePool:
    """Mitsuba scenes kept alive across clips, one per scene structure, retargeted in place (see the module doc)."""

    def __init__(self, max_scenes: int = MAX_POOLED_SCENES):
        self.max_scenes = max_scenes
        self._scenes: OrderedDict[str, PooledScene] = OrderedDict()
        self.builds = 0
        self.retargets = 0

    def get(self, key: str, build) -> tuple[PooledScene, bool]:
        """The pooled scene for ``key`` (built with ``build()`` if missing) and whether it was built now."""
        entry = self._scenes.get(key)
        if entry is not None:
            self._scenes.move_to_end(key)
            return entry, False
        entry = build()
        self._scenes[key] = entry
        self.builds += 1
        while len(self._scenes) > self.max_scenes:
            self._scenes.popitem(last=False)
        return entry, True

    def __len__(self) -> int:
        return len(self._scenes)

    def clear(self) -> None:
        self._scenes.clear()


_POOLS: dict[str, ScenePool] = {}


def scene_pool(mi: ModuleType) -> ScenePool:
    """This process's pool for Mitsuba's current variant."""
    return _POOLS.setdefault(mi.variant(), ScenePool())


def clear_scene_pools() -> None:
    """Empty this process's pools of every Mitsuba variant (``render.stage.release_look``, before Dr.Jit's kernels
    go: its flush is process-wide)."""
    for pool in _POOLS.values():
        pool.clear()


def load_scene(mi: ModuleType, scene: dict):
    """``mi.load_dict(scene)`` with the shapes kept apart and in the dict's order.

    By default load_dict merges a scene's shapes into one (``optimize=True``) through a map keyed by pointers, so
    the shapes' order, and with it the area lights' order and which light a random number picks, followed memory
    addresses: under random lighting (one to three area lights) the same clip and seed rendered other noise in
    about one build in twelve on scalar_rgb."""
    return mi.load_dict(scene, optimize=False)


def _copy_params(src, dst, prefix: str) -> None:
    """Copy every parameter of Mitsuba object ``src`` into scene parameters ``dst`` under ``prefix``.

    Film sizes and flags are structure, identical for a given pool key; they are left
    alone so that no film or object is reallocated. Everything else (transforms,
    colours, texture data, scales; Python floats on scalar_rgb) is the clip's.
    """
    for key in src.keys():
        target = prefix + key
        if target not in dst or key.rsplit(".", 1)[-1] in _STRUCTURE_KEYS:
            continue
        value = src[key]
        if isinstance(value, (bool, str)):
            continue
        # A freshly loaded object's values can be literals, which Dr.Jit bakes into the kernel: the
        # path tracer would compile anew for every clip. Opaque values are kernel inputs instead.
        dst[target] = _opaque(value)


_STRUCTURE_KEYS = {"size", "crop_size", "crop_offset", "allow_thread_reordering"}


def _opaque(value):
    """``value`` made a kernel input rather than a literal Dr.Jit would bake into the kernel."""
    if not isinstance(value, (int, float)):
        import drjit as dr  # imported here: render.backend must pick libLLVM before drjit is first imported

        dr.make_opaque(value)
    return value


class ClipRenderer:
    """Renders the frames of one clip under one variant (one scene, updated in place)."""

    def __init__(self, clip: SimClip, variant: RenderVariant, *, resolution: int, spp: int, run_seed: int,
                 clip_index: int, backend: str = "auto", backgrounds: Backgrounds | None = None,
                 reuse_scenes: bool = True, freeze: bool = True):
        self.mi: ModuleType = load_mitsuba(backend)
        self.clip, self.variant = clip, variant
        self.resolution, self.spp = int(resolution), int(spp)
        self.sampler_seed = seeding.derive_int(run_seed, clip_index, seeding.RENDER, "sampler")

        def stream(*name: str | int) -> np.random.Generator:
            return seeding.rng(run_seed, clip_index, seeding.RENDER, *name)

        self.texture = make_texture(variant.texture, stream("texture"), variant.texture_tile_m)
        backgrounds = backgrounds or Backgrounds(variant, self.resolution)
        # The background is only needed when the first frame is composited: draw it on a helper thread
        # while the scene is set up and the first frames render (a procedural room costs ~50 ms at 224 px).
        self._background = _BACKGROUND_DRAWS.submit(backgrounds.draw, stream("background"))
        # A fixed camera per setting (the sim's ``view_box``), else one framed on the clip's own bounds
        # (synthetic clips, garments, runs simulated before view_box existed).
        box = clip.meta.get("view_box")
        # The view box already holds every pose with room to spare, so it is framed without a margin; the
        # setting's zoom (``view_zoom``: sim.arm_view_zoom for arm clips; absent in clips simulated before it)
        # frames the usual poses closer.
        zoom = variant.zoom * float(clip.meta.get("view_zoom", 1.0))
        self.framing = zoomed(frame_camera(*(np.asarray(b, np.float64) for b in box), margin=1.0) if box
                              else frame_camera(*clip.bounds()), zoom)
        self.lights, lighting_info = emitters(self.mi, variant, self.framing, stream("lighting"))
        self.room = room_shapes(self.mi, variant, self.framing, stream("room"))
        self.camera = draw_camera(variant, stream("camera"))
        self._stream = stream
        self._info = {
            "backend": self.mi.variant(),
            "run_seed": int(run_seed),
            "clip_index": int(clip_index),
            "seed_streams": list(STREAMS),  # clothgap.seeding.rng(run_seed, clip_index, RENDER, stream[, frame])
            "sampler_seed": self.sampler_seed,
            "draws": {  # what the seeded randomizers picked for this clip
                "texture": self.texture.info(),
                "background": None,  # filled in by ``info`` once the draw is done
                "lighting": lighting_info,
                "camera": {**self.camera.info(), "origin": self.framing.origin.tolist(),
                           "target": self.framing.target.tolist(), "fov_deg": self.framing.fov_deg},
            },
        }
        self._bsdf_object = None  # loaded only when a scene is built: every loaded BSDF joins Dr.Jit's
                                  # registry, and a registry that changes changes the compiled path tracer
        self._counts: tuple[int, int] | None = None
        self.scene = None
        self.params = None
        self.rebuilds = 0       # scenes this clip built (pooled: 0 when an existing scene was retargeted)
        self.retargets = 0      # pooled scenes this clip took over
        self.pool = scene_pool(self.mi) if reuse_scenes else None
        # dr.freeze only on CUDA: there replayed frames equal traced ones (benchmarks/render_throughput.py:
        # frozen_rel_error 1e-8 on an H100), while llvm_ad_rgb replays kept the BVH of the recorded frame
        # after the cloth moved (wrong frames), and scalar_rgb has no kernels to record.
        self.freeze = bool(freeze) and reuse_scenes and self.mi.variant().startswith("cuda")
        self._pooled: PooledScene | None = None
        self._capacity: tuple[int, int] | None = None
        self._device_finish: DeviceFinish | None = None  # made on the first render_finished (needs the background)

    # ---------------------------------------------------------------- scene

    @property
    def background(self) -> np.ndarray:
        """Linear RGB (H, W, 3) the cloth is composited over (waits for the draw started in __init__)."""
        return self._background.result()[0]

    @property
    def info(self) -> dict:
        """What the clip was rendered with: backend, seeds and every randomizer's draw (for meta.json)."""
        self._info["draws"]["background"] = self._background.result()[1]
        return self._info

    @property
    def _bsdf(self):
        if self._bsdf_object is None:
            self._bsdf_object = cloth_bsdf(self.mi, self.variant, self.texture)
        return self._bsdf_object

    def _scene_dict(self) -> dict:
        """The scene without the cloth mesh: integrator, camera, lights, room."""
        mi = self.mi
        res = self.resolution
        return {
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
            **self.lights,
            **self.room,
        }

    def _mesh(self, n_vertices: int, n_faces: int, positions, faces, uv):
        mi = self.mi
        props = mi.Properties()
        props["bsdf"] = self._bsdf
        mesh = mi.Mesh("cloth", n_vertices, n_faces, props=props, has_vertex_normals=True,
                       has_vertex_texcoords=True)
        mesh_params = mi.traverse(mesh)
        self._assign(mesh_params, "", positions, faces, uv)
        mesh_params.update()
        return mesh

    def _build(self, positions: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> None:
        """One scene for this clip alone (reuse_scenes=False)."""
        scene = self._scene_dict()
        scene["cloth"] = self._mesh(len(positions), len(faces), positions, faces, uv)
        self.scene = load_scene(self.mi, scene)
        self.params = self.mi.traverse(self.scene)
        self._counts = (len(positions), len(faces))
        self.rebuilds += 1

    def _structure_key(self, capacity: tuple[int, int]) -> str:
        """What must match for two clips to share a scene: everything but the values retargeting copies."""
        def shape(entry):
            if isinstance(entry, dict):
                return {k: shape(v) for k, v in entry.items() if k not in ("to_world", "value", "bitmap", "scale",
                                                                           "radiance", "irradiance", "direction")}
            return type(entry).__name__
        # The field of view (the variant's zoom times the motion's, meta view_zoom) is not retargeted: a frozen
        # render may have baked it in, so clips framed differently (wind and arm under one look) take two scenes.
        return json.dumps({"variant": self.variant.settings(), "resolution": self.resolution,
                           "fov_deg": round(float(self.framing.fov_deg), 9),
                           "capacity": capacity, "lights": shape(self.lights), "room": shape(self.room)},
                          sort_keys=True, default=str)

    def _clip_capacity(self) -> tuple[int, int]:
        clip = self.clip
        counts_v = np.diff(clip.vertex_offsets)
        if clip.fixed_topology:
            return int(counts_v[0]), int(len(clip.faces))
        counts_f = np.diff(clip.face_offsets)
        return _bucket(int(counts_v.max()) + 1), _bucket(int(counts_f.max()))  # +1: a spare vertex for padding

    def _acquire(self, positions, faces, uv) -> None:
        """Take over the pooled scene of this clip's structure and retarget it to this clip."""
        mi = self.mi
        capacity = self._clip_capacity()

        def build() -> PooledScene:
            scene = self._scene_dict()
            p, f, u = self._padded(positions, faces, uv, capacity)
            scene["cloth"] = self._mesh(capacity[0], capacity[1], p, f, u)
            loaded = load_scene(mi, scene)
            return PooledScene(loaded, mi.traverse(loaded), capacity)

        entry, built = self.pool.get(self._structure_key(capacity), build)
        self.rebuilds += int(built)
        if not built:
            self._retarget(entry)
            self.pool.retargets += 1
            self.retargets += 1
        entry.owner = self
        self._pooled, self._capacity = entry, capacity
        self.scene, self.params = entry.scene, entry.params
        self._counts = None  # faces and uv are written on the first update

    def _retarget(self, entry: PooledScene) -> None:
        """Write this clip's camera, lights, room and texture into a pooled scene built for another clip.

        Values are computed here, not copied from freshly loaded Mitsuba objects, wherever the plugin's
        parameters are simple (camera, area lights, constant ambient, room walls, the texture): a new
        emitter, shape or BSDF object would join Dr.Jit's instance registry, and the path tracer's
        virtual calls, hence its kernel, depend on that registry (a CUDA compile per clip again).
        Environment maps and suns go through a loaded copy (``_copy_params``).
        """
        mi, params = self.mi, entry.params

        def put(key: str, value) -> None:
            params[key] = _opaque(value)

        def rgb(entry_: dict) -> object:
            return mi.Color3f(*[float(x) for x in entry_["value"]])

        for name, value in self._scene_dict().items():
            if not isinstance(value, dict) or name == "integrator":
                continue
            kind = value.get("type")
            if name == "sensor":
                put("sensor.to_world", mi.AffineTransform4f(value["to_world"]))
            elif kind == "rectangle":
                put(f"{name}.to_world", mi.AffineTransform4f(value["to_world"]))
                if "emitter" in value:
                    put(f"{name}.emitter.radiance.value", rgb(value["emitter"]["radiance"]))
                if "bsdf" in value and f"{name}.bsdf.reflectance.value" in params:
                    put(f"{name}.bsdf.reflectance.value", rgb(value["bsdf"]["reflectance"]))
            elif kind == "constant":
                put(f"{name}.radiance.value", rgb(value["radiance"]))
            else:
                _copy_params(mi.traverse(mi.load_dict(value)), params, f"{name}.")
        texture_keys = [k for k in params.keys() if k.startswith("cloth.bsdf.") and k.endswith(".data")]
        for key in texture_keys:  # the cloth's colour texture (none for the measured BSDF)
            put(key, mi.TensorXf(np.ascontiguousarray(self.texture.image)))

    def _padded(self, positions, faces, uv, capacity: tuple[int, int]):
        """Geometry padded to the mesh capacity: spare vertices at vertex 0, degenerate faces on the last vertex."""
        n_v, n_f = capacity
        if len(positions) == n_v and len(faces) == n_f:
            return positions, faces, uv
        if len(positions) >= n_v or len(faces) > n_f:
            raise ValueError(f"frame has {len(positions)} vertices / {len(faces)} faces; the pooled mesh holds "
                             f"{n_v} / {n_f} (one vertex spare)")
        pad_v = n_v - len(positions)
        positions = np.concatenate([positions, np.repeat(positions[:1], pad_v, 0)])
        uv = np.concatenate([uv, np.zeros((pad_v, 2), np.asarray(uv).dtype)])
        faces = np.concatenate([faces, np.full((n_f - len(faces), 3), n_v - 1, np.asarray(faces).dtype)])
        return positions, faces, uv

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
        if self.pool is not None:
            if self._pooled is None or self._pooled.owner is not self:  # first frame, or another clip took it
                self._acquire(positions, faces, uv)
            counts = (len(positions), len(faces))
            topology = self._counts is None or not self.clip.fixed_topology
            p, f, u = self._padded(positions, faces, uv, self._capacity)
            self._assign(self.params, "cloth.", p, f if topology else None, u)
            if len(p) > len(positions):
                # Spare vertices belong to no face, so Mitsuba warns that their normals are invalid on every
                # update; they are never shaded (no ray hits a degenerate face), so the warning is noise here.
                level = self.mi.log_level()
                self.mi.set_log_level(self.mi.LogLevel.Error)
                try:
                    self.params.update()
                finally:
                    self.mi.set_log_level(level)
            else:
                self.params.update()
            self._counts = counts
            return
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
        if n == 1:  # the same float32 values as the average below, without its float64 copies
            self._set_geometry(t)
            return np.array(self._render(spp, (self.sampler_seed + t) & 0xFFFFFFFF), np.float32)  # owned copy
        total = np.zeros((self.resolution, self.resolution, 4), np.float64)
        for k in range(n):
            self._set_geometry(t + k / n)
            seed = (self.sampler_seed + t * n + k) & 0xFFFFFFFF
            total += np.asarray(self._render(spp, seed), np.float64)
        return (total / n).astype(np.float32)

    def render_linear(self, t: int):
        """Frame t's linear cloth RGBA left on the device: a flat Float (H*W*4) of Mitsuba's JIT variant.

        The same float32 values as ``render_hdr`` (the motion-blur average in float64, as there)."""
        n = self.variant.motion_blur_subframes
        spp = max(1, self.spp // n)
        if n == 1:
            self._set_geometry(t)
            return self._render(spp, (self.sampler_seed + t) & 0xFFFFFFFF).array
        import drjit as dr

        float64 = dr.float64_array_t(self.mi.Float)
        total = None
        for k in range(n):
            self._set_geometry(t + k / n)
            sub = float64(self._render(spp, (self.sampler_seed + t * n + k) & 0xFFFFFFFF).array)
            total = sub if total is None else total + sub
            dr.eval(total)  # the sum is taken before the next subframe moves the cloth
        return self.mi.Float(total / dr.opaque(float64, n))  # an opaque divisor: an exact division, as numpy's

    @property
    def device_finish_unsupported(self) -> str | None:
        """None when ``render_finished`` can finish this clip's frames on the device; else why not."""
        return device_unsupported(self.mi.variant(), self.variant)

    @property
    def device_finisher(self) -> DeviceFinish:
        """The clip's ``DeviceFinish`` (made on first use: it uploads the background, waiting for its draw)."""
        if self._device_finish is None:
            self._device_finish = DeviceFinish(self.mi, self.variant, self.camera, self.background)
        return self._device_finish

    def render_finished(self, t: int, hdr: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Frame t rendered and finished on the device: (the uint8 sRGB frame ``finish`` gives, (H, W, 3);
        the linear RGBA (H, W, 4) float32 ``render_hdr`` gives when ``hdr``, else None)."""
        return self.read_finished(self.launch_finished(t), hdr)

    def launch_finished(self, t: int):
        """Frame t rendered and finished on the device, its kernels launched but not waited for: a handle
        for ``read_finished``. Evaluated now, so that moving the cloth for a later frame cannot reach it."""
        import drjit as dr

        finisher = self.device_finisher
        linear = self.render_linear(t)
        codes = finisher(linear)
        dr.eval(linear, codes)
        return linear, codes

    def read_finished(self, launched, hdr: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """``render_finished``'s result from ``launch_finished``'s handle (waits for the device)."""
        linear, codes = launched
        ldr = self.device_finisher.to_host(codes)
        if not hdr:
            return ldr, None
        res = self.resolution
        return ldr, np.array(linear, np.float32).reshape(res, res, 4)

    def _render(self, spp: int, seed: int):
        mi = self.mi
        if not self.freeze:
            return mi.render(self.scene, spp=spp, seed=seed)
        entry = self._pooled
        if entry.frozen is None:
            import drjit as dr

            def render(scene, seed, spp):
                return mi.render(scene, spp=spp, seed=seed)

            entry.frozen = dr.freeze(render)
        # The seed goes in as a JIT variable (a new Python int would be a new recording); spp is static.
        return entry.frozen(self.scene, mi.UInt32(seed), spp)

    def finish(self, hdr: np.ndarray, t: int) -> np.ndarray:
        """Frame t's 8-bit sRGB image the network reads, from the cloth's linear RGBA."""
        rgb, alpha = hdr[..., :3], hdr[..., 3:4]
        composite = rgb + (1.0 - np.clip(alpha, 0.0, 1.0)) * self.background  # rgb is premultiplied by coverage
        noise = self._stream("noise", t) if adds_noise(self.variant) else None
        recorded = apply_camera(composite, self.variant, self.camera, noise)
        return tonemap(recorded, self.variant.tonemap)

    def render_frame(self, t: int) -> Frame:
        hdr = self.render_hdr(t)
        return Frame(hdr=hdr, ldr=self.finish(hdr, t))
