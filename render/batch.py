"""Many frames per Mitsuba launch: K frames of a clip side by side in one scene, one ``batch`` sensor.

One ``mi.render`` call per frame leaves a GPU mostly idle at 224 px (launch,
BVH refit and host round trip cost as much as the path tracing), so
``BatchRenderer`` puts K *slots* into one scene and renders them with Mitsuba's
``batch`` sensor into one film K frames wide. Slot k holds the clip's cloth at
frame t0 + k, the clip's camera, lights and room, each rigidly moved into a cell
of its own; the film is cut back into K frames that go through the same
compositing and tone mapping as the one-frame path (``ClipRenderer.finish``).
Every per-clip draw (texture, background, lights, camera effects, noise) comes
from the same ``ClipRenderer`` and so from the same seeds: a clip id looks the
same either way, up to Monte Carlo noise.

Keeping the slots from seeing or lighting each other, exactly in expectation:

* Each slot is rotated so its camera looks straight down (-z) and translated to
  a cell of a horizontal grid. A rigid motion of camera, cloth, lights and room
  together does not change the image, provided the environment is the same in
  every direction, which is why only lightings whose infinite emitters are all
  ``constant`` are batched (``fixed``, the paper's studio); ``random`` and
  ``daylight`` (environment maps, a sun) fall back to one frame per launch.
* Each slot is enclosed by a black shell that emits the ambient radiance
  inward: a sphere around the camera, large enough to hold everything of the
  slot, with a window where the camera looks out, continued by a conical
  tunnel along the view frustum. From inside the shell every direction shows
  the ambient radiance, as the ``constant`` emitter did; nothing from outside
  gets in except through the tunnel, and what leaves through a tunnel moves
  downward, below every slot, where a shared ``constant`` emitter supplies the
  ambient again. Camera rays that miss the cloth leave through the tunnel, so
  alpha is still cloth coverage and the (hidden) ambient is not in the HDR.
* Meshes whose vertex or face count changes between frames (adaptive
  remeshing) are allocated for the clip's largest frame; smaller frames are
  padded with unreferenced vertices and degenerate faces, which no ray hits.

What batching costs, and must be reported with its speed:

* Noise. The path tracer picks the light for next-event estimation among all
  emitters of the scene, so a slot's own key light is sampled about K times
  less often than in a one-frame scene (the others are occluded). Images are
  equal in expectation but noisier at the same spp (see the benchmark's
  ``noise`` figures).
* Precision. Mitsuba offsets secondary rays by about 9e-5 * (1 + |p|), so a
  slot far from the origin gets a slightly larger self-intersection offset
  (millimetres for a 4x4 grid instead of tenths); the grid is kept centred and
  tight for this reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from render.scene import ClipRenderer, Frame

ENCLOSURE_MARGIN = 1.05  # the shell's radius over the farthest point of the slot, seen from its camera
WINDOW_MARGIN = 1.1      # the window's half-angle over the frustum's diagonal half-angle
TUNNEL_LENGTH = 2.0      # the tunnel reaches this many shell radii from the camera
CELL_SPACING = 2.1       # grid spacing in shell radii (the tunnel's mouth has a radius of about one)


def batchable(renderer: ClipRenderer) -> str | None:
    """None if the clip's scene can go into a batch; otherwise why not (for meta and logs)."""
    for name, entry in renderer.lights.items():
        kind = entry.get("type")
        if kind == "rectangle":
            continue
        if kind != "constant":
            return (f"lighting {renderer.variant.lighting!r} has a {kind!r} emitter ({name}); only constant "
                    "environments survive rotating the slots")
    for name, entry in renderer.room.items():
        if entry.get("type") != "rectangle":
            return f"room shape {name} is a {entry.get('type')!r}, not a rectangle"
    return None


def _rotation_to_down(direction: np.ndarray) -> np.ndarray:
    """The rotation taking the view ``direction`` to -z and world up (+z) to +y in the image's frame."""
    v = direction / np.linalg.norm(direction)
    right = np.cross(v, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(v, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, v)
    return np.stack([right, up, -v])  # rows: right -> x, up -> y, view -> -z (a proper rotation)


def _rectangle_corners(to_world: np.ndarray) -> np.ndarray:
    corners = np.array([[-1, -1, 0, 1], [1, -1, 0, 1], [1, 1, 0, 1], [-1, 1, 0, 1]], np.float64)
    return (corners @ to_world.T)[:, :3]


def enclosure_mesh(radius: float, window_deg: float, tunnel: float = TUNNEL_LENGTH,
                   rings: int = 24, segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A shell around the origin, facing inward: a sphere open at the bottom around -z, then a cone outward.

    The profile runs from the top pole down the sphere to the window's rim
    (polar angle 180 - window_deg), then along the cone through the origin out
    to ``tunnel * radius``. Returns (vertices (V, 3), faces (F, 3)), wound so
    that the normals point inward (toward the axis and the origin).
    """
    edge = math.pi - math.radians(window_deg)
    theta = np.linspace(0.0, edge, rings + 1)[1:]
    profile = [(radius * np.sin(t), radius * np.cos(t)) for t in theta]
    for s in np.linspace(1.0, tunnel, max(2, rings // 4) + 1)[1:]:
        profile.append((s * radius * np.sin(edge), s * radius * np.cos(edge)))
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    verts = [[0.0, 0.0, radius]]  # the top pole
    for rho, z in profile:
        verts += [[rho * np.cos(p), rho * np.sin(p), z] for p in phi]
    verts = np.asarray(verts, np.float64)
    faces = []
    for j in range(segments):  # the fan around the pole
        faces.append([0, 1 + (j + 1) % segments, 1 + j])
    for i in range(len(profile) - 1):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        for j in range(segments):
            j1 = (j + 1) % segments
            faces.append([a + j, a + j1, b + j1])
            faces.append([a + j, b + j1, b + j])
    faces = np.asarray(faces, np.int64)
    # Wind every face inward: on a surface of revolution its normal then points toward the axis.
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    normal = np.cross(v1 - v0, v2 - v0)
    radial = (v0 + v1 + v2) / 3 * np.array([1.0, 1.0, 0.0])
    outward = np.einsum("ij,ij->i", normal, radial) > 0
    faces[outward] = faces[outward][:, ::-1]
    return verts, faces


@dataclass(frozen=True)
class SlotPose:
    """Where a slot goes: p_world = offset + rotation @ (p_clip - camera_origin)."""

    rotation: np.ndarray
    camera: np.ndarray
    offset: np.ndarray

    def points(self, p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, np.float64) - self.camera) @ self.rotation.T + self.offset

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.offset - self.rotation @ self.camera
        return m


def _ambient_and_rectangles(emitters: dict) -> tuple[np.ndarray, dict]:
    """The summed radiance of the ``constant`` emitters (the ambient) and the other emitters (rectangles) by name."""
    ambient = np.zeros(3)
    rectangles = {}
    for name, entry in emitters.items():
        if entry["type"] == "constant":
            ambient += np.asarray(entry["radiance"]["value"], np.float64)
        else:
            rectangles[name] = entry
    return ambient, rectangles


def grid_offsets(count: int, spacing: float) -> np.ndarray:
    """``count`` points of a square-ish grid in the z = 0 plane, centred on the origin."""
    cols = math.ceil(math.sqrt(count))
    rows = math.ceil(count / cols)
    out = [((c - (cols - 1) / 2) * spacing, (r - (rows - 1) / 2) * spacing, 0.0)
           for r in range(rows) for c in range(cols)][:count]
    return np.asarray(out, np.float64)


class BatchRenderer:
    """Renders a clip ``frames_per_launch`` frames at a time in one scene (see the module's docstring)."""

    def __init__(self, renderer: ClipRenderer, frames_per_launch: int):
        reason = batchable(renderer)
        if reason is not None:
            raise ValueError(f"clip cannot be batched: {reason}")
        self.r = renderer
        self.mi = renderer.mi
        self.clip = renderer.clip
        self.k = max(1, min(int(frames_per_launch), self.clip.num_frames))
        self.launches = 0
        self._build()

    # ---------------------------------------------------------------- scene

    def _capacity(self) -> tuple[int, int]:
        clip = self.clip
        counts_v = np.diff(clip.vertex_offsets)
        if clip.fixed_topology:
            return int(counts_v[0]), int(len(clip.faces))
        counts_f = np.diff(clip.face_offsets)
        return int(counts_v.max()) + 1, int(counts_f.max())  # +1: a spare vertex for degenerate padding faces

    def _build(self) -> None:
        """The scene of K slots (see the module's docstring), its cloth at the clip's first frame."""
        mi, r = self.mi, self.r
        framing = r.framing
        origin, target = np.asarray(framing.origin, np.float64), np.asarray(framing.target, np.float64)
        rotation = _rotation_to_down(target - origin)
        ambient, rectangles = _ambient_and_rectangles({**r.lights, **r.room})
        radius, window = self._enclosure(origin, rectangles)
        shell = enclosure_mesh(radius, window)
        offsets = grid_offsets(self.k, CELL_SPACING * radius * max(1.0, TUNNEL_LENGTH * math.sin(math.radians(window))))
        self.poses = [SlotPose(rotation, origin, o) for o in offsets]

        black = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
        scene = self._scene_dict(ambient)
        self._cloth_keys = []
        for i, pose in enumerate(self.poses):
            # Objects are instantiated here, one by one, rather than by load_dict: it merges a scene's shape
            # dicts through a map keyed by pointers, so their order, the area lights' and so which light a random
            # number picks would follow memory addresses (render.scene.load_scene); built objects keep theirs.
            self._add_slot_view(scene, i, pose, target, rotation, rectangles)
            if ambient.any():
                scene[f"shell_{i:03d}"] = self._shell(i, pose, shell, ambient, black)
            key = f"cloth_{i:03d}"
            scene[key] = self._cloth(key, pose)
            self._cloth_keys.append(key)
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        self.radius, self.window_deg = radius, window
        r.rebuilds += 1

    def _enclosure(self, origin: np.ndarray, rectangles: dict) -> tuple[float, float]:
        """The shell's radius, large enough to hold every frame's cloth, the lights and the room seen from the
        camera at ``origin``, and its window's half-angle in degrees."""
        lo, hi = self.clip.bounds()
        box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        points = [box] + [_rectangle_corners(np.asarray(e["to_world"].matrix, np.float64))
                          for e in rectangles.values()]
        reach = max(float(np.linalg.norm(np.concatenate(points) - origin, axis=1).max()), 1e-3)
        half_diag = math.degrees(math.atan(math.tan(math.radians(self.r.framing.fov_deg) / 2) * math.sqrt(2)))
        return ENCLOSURE_MARGIN * reach, min(WINDOW_MARGIN * half_diag, 80.0)

    def _scene_dict(self, ambient: np.ndarray) -> dict:
        """The scene without its slots: the integrator, the ``batch`` sensor K frames wide, the ambient outside."""
        r, res = self.r, self.r.resolution
        return {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": r.variant.max_depth, "hide_emitters": True},
            "sensor": {
                "type": "batch",
                "film": {"type": "hdrfilm", "width": res * self.k, "height": res, "pixel_format": "rgba",
                         "component_format": "float32", "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": r.spp},
            },
            # What leaves through the tunnels sees the ambient, as it would have left the one-slot scene.
            # It is reached only by rays that already left a slot, so next-event estimation never picks it
            # (sampling weight 0): those picks would all be occluded by the shells and only add noise.
            "ambient_outside": {"type": "constant", "radiance": {"type": "rgb", "value": ambient.tolist()},
                                "sampling_weight": 0.0},
        }

    def _add_slot_view(self, scene: dict, i: int, pose: SlotPose, target: np.ndarray, rotation: np.ndarray,
                       rectangles: dict) -> None:
        """Slot ``i``'s camera (a sub-sensor of the batch) and its rectangle lights, moved into its cell."""
        mi, res = self.mi, self.r.resolution
        to_world = mi.ScalarTransform4f(pose.matrix().tolist())
        scene["sensor"][f"s{i:03d}"] = mi.load_dict({
            "type": "perspective", "fov": self.r.framing.fov_deg,
            "to_world": mi.ScalarTransform4f().look_at(origin=pose.offset.tolist(),
                                                       target=pose.points(target[None])[0].tolist(),
                                                       up=(rotation @ np.array([0.0, 0.0, 1.0])).tolist()),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
        })
        for name, entry in rectangles.items():
            scene[f"{name}_{i:03d}"] = mi.load_dict({**entry, "to_world": to_world @ entry["to_world"]})

    def _shell(self, i: int, pose: SlotPose, shell: tuple[np.ndarray, np.ndarray], ambient: np.ndarray, black):
        """Slot ``i``'s black shell, emitting the ambient radiance inward, around its camera."""
        mi = self.mi
        shell_v, shell_f = shell
        props = mi.Properties()
        props["bsdf"] = black
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": ambient.tolist()}})
        mesh = mi.Mesh(f"shell_{i:03d}", len(shell_v), len(shell_f), props=props)
        sp = mi.traverse(mesh)
        sp["vertex_positions"] = type(sp["vertex_positions"])((shell_v + pose.offset).astype(np.float32).ravel())
        sp["faces"] = type(sp["faces"])(shell_f.astype(np.uint32).ravel())
        sp.update()
        return mesh

    def _cloth(self, key: str, pose: SlotPose):
        """A slot's cloth mesh, sized for the clip's largest frame, holding the first frame."""
        mi, r = self.mi, self.r
        n_v, n_f = self._capacity()
        props = mi.Properties()
        props["bsdf"] = r._bsdf
        mesh = mi.Mesh(key, n_v, n_f, props=props, has_vertex_normals=True, has_vertex_texcoords=True)
        mp = mi.traverse(mesh)
        positions, faces, uv = self._padded(0, pose, n_v, n_f)
        r._assign(mp, "", positions, faces, uv)
        mp.update()
        return mesh

    def _padded(self, t: float, pose: SlotPose, n_v: int, n_f: int):
        positions, faces, uv = self.r._geometry(t)
        positions = pose.points(positions)
        if len(positions) == n_v and len(faces) == n_f:
            return positions, faces, uv
        pad_v = n_v - len(positions)
        positions = np.concatenate([positions, np.repeat(positions[:1], pad_v, 0)])
        uv = np.concatenate([uv, np.zeros((pad_v, 2), uv.dtype)])
        faces = np.concatenate([faces, np.full((n_f - len(faces), 3), n_v - 1, faces.dtype)])
        return positions, faces, uv

    def _set_geometry(self, times: list[float]) -> None:
        n_v, n_f = self._capacity()
        fixed = self.clip.fixed_topology
        for key, pose, t in zip(self._cloth_keys, self.poses, times):
            positions, faces, uv = self._padded(t, pose, n_v, n_f)
            self.r._assign(self.params, key + ".", positions, None if fixed else faces, uv)
        self.params.update()

    # ---------------------------------------------------------------- frames

    def render_hdr(self, frames: list[int]) -> list[np.ndarray]:
        """Linear cloth RGBA of up to K frames in one launch (per motion-blur subframe); one array per frame."""
        if not 0 < len(frames) <= self.k:
            raise ValueError(f"a launch takes 1..{self.k} frames, got {len(frames)}")
        r = self.r
        n = r.variant.motion_blur_subframes
        spp = max(1, r.spp // n)
        res = r.resolution
        idle = [frames[-1]] * (self.k - len(frames))  # unused slots repeat the last frame; their pixels are dropped
        total = np.zeros((res, res * self.k, 4), np.float64)
        for sub in range(n):
            self._set_geometry([t + sub / n for t in list(frames) + idle])
            seed = (r.sampler_seed + frames[0] * n + sub) & 0xFFFFFFFF
            total += np.asarray(self.mi.render(self.scene, spp=spp, seed=seed), np.float64)
        self.launches += 1
        total /= n
        return [total[:, i * res:(i + 1) * res].astype(np.float32) for i in range(len(frames))]

    def hdr_frames(self):
        """Every frame of the clip, in order, as ``(t, hdr)``; K frames per launch."""
        for t0 in range(0, self.clip.num_frames, self.k):
            ts = list(range(t0, min(t0 + self.k, self.clip.num_frames)))
            yield from zip(ts, self.render_hdr(ts))

    def frames(self):
        """Every frame of the clip, in order, as ``(t, Frame)`` (HDR and the tone-mapped frame)."""
        for t, hdr in self.hdr_frames():
            yield t, Frame(hdr=hdr, ldr=self.r.finish(hdr, t))
