"""The paper's motion sub-space (Section 4.3): what drives each simulated clip, one registry entry per motion.

``wind``: the cloth hangs under gravity, gathered to a fraction of its width
like a curtain, in one of two poses (the paper's Fig. 8 shows two): ``rod``, the
whole top edge pinned along a wave, or ``corners``, only the two top corners
pinned. The gathering puts folds into the cloth whose width and persistence
depend on its bending stiffness, and the sag on its stretching stiffness. After
a short settling period a constant-velocity wind, mostly horizontal and into
the cloth, switches on and the recorded frames start. Pose, gathering, wind
speed and direction are drawn per clip from the clip's motion random stream.

``arm``: the cloth lies draped over a horizontal capsule arm (upper arm and
forearm along x, elbow at the origin); when recording starts the forearm swings
horizontally (about the vertical axis through the elbow) through a fixed angle
(``ARM_ANGLE_DEG``) at a speed drawn per clip. The flap on the inside of the
bend is compressed into folds whose shape shows bending stiffness; the outside
flap is swung out. The sweep is horizontal because a vertical one cuts edges
through the elbow (docs/simulation.md, "Arm contact"). The cloth's placement along and across the arm is drawn per clip,
across within 2 cm of centre so that it drapes nearly symmetrically; friction (``SolverParams.friction``,
static and sliding, inside the implicit solve) holds it there while the forearm turns.
``arm_contact_report`` tells a clip of a cloth on the arm from one of a cloth falling off it.

A motion builds a ``ClipScene``: the cloth at rest (``ClothSpec`` without wind)
plus what changes when recording starts, and the parameters written to the
clip's ``meta.json``. ``MOTIONS`` registers each motion by name, with its scene
builder and the box its fixed camera frames; adding a motion is writing those
two functions and one ``Motion`` entry. This module imports no Warp, so config
checks read the registry cheaply.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from sim.materials import Material
from sim.mesh import ClothMesh
from sim.specs import ArmSpec, ClothSpec

# Wind speed range, m/s. The basis fabric weighs 0.28 kg/m^2 (2.8 Pa under gravity);
# 1 to 2.5 m/s gives 0.6 to 3.8 Pa of dynamic pressure: from a sway to a billow.
WIND_SPEED_MPS = (1.0, 2.5)
WIND_AZIMUTH_DEG = 35.0        # max deviation from the cloth's normal, in the horizontal plane
WIND_ELEVATION_DEG = 10.0      # max deviation from horizontal
POSES = ("rod", "corners")
GATHER_RATIO = (0.7, 0.9)      # pinned width / cloth width
GATHER_WAVES = (2, 5)          # half-waves across the gathered width, inclusive

ARM_RADIUS_M = 0.04
ARM_UPPER_M = 0.35             # shoulder -> elbow
ARM_FORE_M = 0.30              # elbow -> hand
ARM_ANGLE_DEG = 90.0           # the forearm's fixed sweep
ARM_SPEED_DEG_S = (120.0, 300.0)
ARM_ALONG_M = 0.05             # max shift of the cloth's centre along the arm
ARM_ACROSS_M = 0.02            # max shift across: flaps within 4 cm of each other (0.05 m let one side outweigh)


@dataclass
class ClipScene:
    spec: ClothSpec                    # the cloth at rest, no wind
    wind: np.ndarray                   # (3,) m/s, switched on when recording starts
    motion_params: dict = field(default_factory=dict)


def hanging_positions(mesh: ClothMesh, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A cloth hanging flat in the x-z plane (u along x, v up), its top edge at z = size_m, centred on x = 0.
    Returns the positions and the pinned top-edge vertex indices (left to right)."""
    uv = mesh.uv
    pos = np.stack([uv[:, 0] - 0.5 * size_m, np.zeros(len(uv)), uv[:, 1]], axis=1)
    top = np.flatnonzero(np.isclose(uv[:, 1], uv[:, 1].max()))
    return pos, top[np.argsort(uv[top, 0])]


def gathered_positions(mesh: ClothMesh, size_m: float, ratio: float, waves: int) -> tuple[np.ndarray, np.ndarray]:
    """A hanging cloth gathered to ``ratio`` of its width: every horizontal line follows the same sine
    wave (``waves`` half-waves) whose arc length equals the cloth's width, so the cloth starts unstretched."""
    pos, top = hanging_positions(mesh, size_m)
    width = ratio * size_m
    amplitude, arc_length, xs = _gather_wave(size_m, ratio, waves)
    x = np.interp(mesh.uv[:, 0], arc_length, xs)     # arc length (= u) -> position along the wave
    pos[:, 0] = x - 0.5 * width
    pos[:, 1] = amplitude * np.sin(np.pi * waves * x / width)
    return pos, top


@functools.lru_cache(maxsize=64)
def _gather_wave(size_m: float, ratio: float, waves: int) -> tuple[float, np.ndarray, np.ndarray]:
    """The gathering sine's amplitude, its arc length along ``xs`` and ``xs``. Cached: a batch of clips
    with one gathering (the speed-only nuisance) bisects once instead of once a clip."""
    width = ratio * size_m
    xs = np.linspace(0.0, width, 4001)
    dx, shape = np.diff(xs), np.sin(np.pi * waves * xs / width)

    def arc(amplitude: float) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum(np.hypot(dx, np.diff(amplitude * shape)))])

    lo, hi = 0.0, size_m
    for _ in range(60):                               # bisection on the wave's amplitude
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if arc(mid)[-1] > size_m else (mid, hi)
    amplitude = 0.5 * (lo + hi)
    arc_length = arc(amplitude)
    arc_length.flags.writeable = xs.flags.writeable = False    # shared by every caller
    return amplitude, arc_length, xs


def wind_scene(mesh: ClothMesh, size_m: float, material: Material, rng: np.random.Generator,
               nuisance: str = "full") -> ClipScene:
    """A gathered hanging cloth and a constant wind, all drawn from ``rng`` (the clip's motion stream).

    ``nuisance="speed"`` keeps only the wind speed random (rod pose, the middle gathering, wind along
    the cloth's normal): the paper's "external force magnitude". The draws are made either way, so a
    clip's speed is the same under both.
    """
    pose = POSES[int(rng.integers(len(POSES)))]
    ratio = rng.uniform(*GATHER_RATIO)
    waves = int(rng.integers(GATHER_WAVES[0], GATHER_WAVES[1] + 1))
    speed = rng.uniform(*WIND_SPEED_MPS)
    azimuth = math.radians(rng.uniform(-WIND_AZIMUTH_DEG, WIND_AZIMUTH_DEG))
    elevation = math.radians(rng.uniform(-WIND_ELEVATION_DEG, WIND_ELEVATION_DEG))
    if nuisance == "speed":
        pose, ratio, waves, azimuth, elevation = "rod", sum(GATHER_RATIO) / 2, 3, 0.0, 0.0
    elif nuisance != "full":
        raise ValueError(f"nuisance={nuisance!r}: expected 'full' or 'speed'")
    wind = speed * np.array([math.sin(azimuth) * math.cos(elevation), math.cos(azimuth) * math.cos(elevation),
                             math.sin(elevation)])
    pos, top = gathered_positions(mesh, size_m, ratio, waves)
    pinned = top if pose == "rod" else top[[0, -1]]
    spec = ClothSpec(mesh, pos, material.stretching, material.bending, material.density, pinned=pinned)
    params = {"pose": pose, "gather_ratio": ratio, "gather_half_waves": waves, "wind_speed_mps": speed, "wind_azimuth_deg": math.degrees(azimuth),
              "wind_elevation_deg": math.degrees(elevation), "wind_velocity_mps": wind.tolist()}
    return ClipScene(spec, wind, params)


def arm_scene(mesh: ClothMesh, size_m: float, material: Material, rng: np.random.Generator,
              start_s: float, fps: float, frames: int, nuisance: str = "full") -> ClipScene:
    """A cloth laid flat over a capsule arm, draping during settling; the forearm starts turning at ``start_s``
    (the first recorded frame). All draws come from ``rng`` (the clip's motion stream).

    ``nuisance="speed"`` keeps only the forearm's speed random and centres the cloth on the elbow (the
    placement hides the material from the geometry: docs/learnability.md, section 4); the placement is
    still drawn, so a clip's speed is the same under both."""
    speed = math.radians(rng.uniform(*ARM_SPEED_DEG_S))
    along, across = rng.uniform(-1.0, 1.0, size=2) * (ARM_ALONG_M, ARM_ACROSS_M)
    if nuisance == "speed":
        along, across = 0.0, 0.0
    elif nuisance != "full":
        raise ValueError(f"nuisance={nuisance!r}: expected 'full' or 'speed'")
    uv = mesh.uv
    height = ARM_RADIUS_M + 0.01
    pos = np.stack([uv[:, 0] - 0.5 * size_m + along, uv[:, 1] - 0.5 * size_m + across,
                    np.full(len(uv), height)], axis=1)
    sweep = math.radians(ARM_ANGLE_DEG)
    arm = ArmSpec(shoulder=(-ARM_UPPER_M, 0.0, 0.0), elbow=(0.0, 0.0, 0.0), forearm=(ARM_FORE_M, 0.0, 0.0),
                  axis=(0.0, 0.0, 1.0), radius=ARM_RADIUS_M, omega=speed, max_angle=sweep, t0=start_s)
    spec = ClothSpec(mesh, pos, material.stretching, material.bending, material.density, arm=arm)
    params = {"arm_speed_deg_s": math.degrees(speed), "arm_sweep_deg": ARM_ANGLE_DEG,
              "cloth_offset_m": [float(along), float(across)], "arm_radius_m": ARM_RADIUS_M,
              "shoulder": list(arm.shoulder), "elbow": list(arm.elbow), "forearm_at_rest": list(arm.forearm),
              "rotation_axis": list(arm.axis),
              "note": "frame t is (t + 1) / fps seconds after the forearm starts turning",
              "forearm_angle_deg_per_frame": [min(math.degrees(speed) * (t + 1) / fps, ARM_ANGLE_DEG)
                                              for t in range(frames)]}
    return ClipScene(spec, np.zeros(3), params)


def wind_view_box(size_m: float) -> tuple[list[float], list[float]]:
    """The wind camera's box: the cloth hangs from z = size_m down to 0 (more when stretched), blown mostly
    toward +y."""
    s = float(size_m)
    return [-0.55 * s, -0.25 * s, -0.15 * s], [0.55 * s, 0.85 * s, 1.05 * s]


def arm_view_box(size_m: float) -> tuple[list[float], list[float]]:
    """The arm camera's box: the cloth lies across the arm (x) around the elbow, its flaps hanging about
    size_m / 2 below; the forearm's swing carries its part toward +-y, i.e. toward or away from the camera."""
    s = float(size_m)
    half = 0.6 * s + ARM_RADIUS_M
    return [-half, -half, -0.55 * s - ARM_RADIUS_M], [half, half, 2 * ARM_RADIUS_M]


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``v`` turned by ``angle`` radians about the unit ``axis`` (Rodrigues)."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * float(np.dot(axis, v)) * (1.0 - c)


def _segment_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip((x - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[:, None] * ab), axis=1)


def arm_contact_report(frames, motion_params: dict, cloth_size_m: float, fall_margin_m: float | None = None,
                       touch_m: float = 0.02) -> dict:
    """Whether an ``arm`` clip shows a cloth on the arm or a cloth falling off it.

    ``frames``: the recorded positions, (T, V, 3) or a sequence of (V_t, 3) (adaptive clips);
    ``motion_params``: the clip's ``meta["motion_params"]`` (``arm_scene``'s). Returns, at the last frame
    (distances in metres, "drop" = how far below the arm's axis, i.e. the elbow's height):

    * ``centroid_drop_m``: of the cloth's centroid (``max_centroid_drop_m``: the largest over all frames);
    * ``lowest_drop_m``: of the lowest vertex;
    * ``fallen_fraction``: of the vertices lower than the arm's lowest point minus ``fall_margin_m``
      (default 0.6 x the cloth's side: a draped vertex hangs at most half the cloth plus the placement offset,
      0.3 m of a 0.5 m cloth, below the arm's top, i.e. 0.22 m below its lowest point);
    * ``touching_fraction``: of the vertices within ``touch_m`` of the arm's surface (upper arm or forearm at
      that frame's angle);
    * ``on_arm``: no vertex fallen and some touching.
    """
    frames = [np.asarray(f, dtype=np.float64) for f in frames]
    if not frames:
        raise ValueError("arm_contact_report needs at least one frame")
    radius = float(motion_params["arm_radius_m"])
    shoulder, elbow = np.asarray(motion_params["shoulder"], float), np.asarray(motion_params["elbow"], float)
    forearm = np.asarray(motion_params["forearm_at_rest"], float)
    axis = np.asarray(motion_params["rotation_axis"], float)
    axis = axis / np.linalg.norm(axis)
    angles = motion_params["forearm_angle_deg_per_frame"]
    margin = 0.6 * cloth_size_m if fall_margin_m is None else fall_margin_m
    up = elbow[2]
    x = frames[-1]
    hand = elbow + _rotate(forearm, axis, math.radians(angles[min(len(frames), len(angles)) - 1]))
    dist = np.minimum(_segment_distance(x, shoulder, elbow), _segment_distance(x, elbow, hand)) - radius
    fallen = float(np.mean(x[:, 2] < up - radius - margin))
    touching = float(np.mean(dist < touch_m))
    return {"frames": len(frames),
            "centroid_drop_m": float(up - x[:, 2].mean()),
            "max_centroid_drop_m": float(max(up - f[:, 2].mean() for f in frames)),
            "lowest_drop_m": float(up - x[:, 2].min()),
            "fallen_fraction": fallen,
            "touching_fraction": touching,
            "on_arm": bool(fallen == 0.0 and touching > 0.0)}


def arm_clip_report(clip) -> dict:
    """``arm_contact_report`` of a saved ``sim.clip.SimClip`` of an ``arm`` setting."""
    return arm_contact_report([pos for pos, _, _ in clip.frames()], clip.meta["motion_params"],
                              float(clip.meta["cloth_size_m"]))


# ---------------------------------------------------------------- the registry

@dataclass(frozen=True)
class Motion:
    """One registered motion: what drives its clips and where the camera looks."""

    name: str
    description: str
    # (mesh, material, rng, cfg: sim.config.SimConfig) -> the clip's scene; rng is the clip's motion stream.
    scene: Callable[[ClothMesh, Material, np.random.Generator, object], ClipScene]
    # cloth side in metres -> (low, high) corners of the box a fixed camera frames for every clip of the motion
    # (``meta["view_box"]``, used by render). It holds every pose the motion reaches, and its depth (y) is no
    # larger than its width (x), so the camera looks along y at the cloth's face. The same for every clip of a
    # setting, as the paper's "controlled camera settings": a cloth that stretches, sags or swings more then
    # looks bigger or moves further in the image (a camera framed on each clip would scale that away).
    view_box: Callable[[float], tuple[list[float], list[float]]]
    # cfg (sim.config.SimConfig) -> the camera's field of view narrowed by this factor from the box's framing
    # (``meta["view_zoom"]``, which render multiplies into a variant's own zoom): the box holds the rarest poses,
    # so where the cloth's usual poses fill only part of it a setting may frame them closer, and a few pixels of
    # an extreme pose then leave the frame. A setting of the run (sim.arm_view_zoom), so that a run's clips share
    # one framing whatever code resumes it.
    view_zoom: Callable[[object], float] = lambda cfg: 1.0
    # The sim settings only this motion's clips read: a run with none of its clips may change them at any time.
    settings: tuple[str, ...] = ()


def _wind_clip(mesh: ClothMesh, material: Material, rng: np.random.Generator, cfg) -> ClipScene:
    return wind_scene(mesh, cfg.cloth_size_m, material, rng, cfg.wind_nuisance)


def _arm_clip(mesh: ClothMesh, material: Material, rng: np.random.Generator, cfg) -> ClipScene:
    # The forearm starts turning with the first recorded frame, after settling.
    return arm_scene(mesh, cfg.cloth_size_m, material, rng, cfg.settle_s, cfg.fps, cfg.frames, cfg.arm_nuisance)


MOTIONS: dict[str, Motion] = {m.name: m for m in (
    Motion("wind", "a gathered cloth hanging from a rod or its corners, blown by a constant wind "
                   "(sim.wind_nuisance: what is drawn per clip)", _wind_clip, wind_view_box,
           settings=("wind_nuisance",)),
    Motion("arm", f"a cloth draped over a capsule arm whose forearm swings through {ARM_ANGLE_DEG:g} degrees "
                  "(sim.arm_nuisance: what is drawn per clip; sim.arm_view_zoom: how close the camera frames it)",
           _arm_clip, arm_view_box, view_zoom=lambda cfg: cfg.arm_view_zoom,
           settings=("arm_nuisance", "arm_view_zoom")),
)}


def get_motion(name: str) -> Motion:
    """The motion called ``name``; an unknown name is an error listing the known ones."""
    if name not in MOTIONS:
        raise ValueError(f"unknown motion {name!r}; known motions: {', '.join(MOTIONS)}")
    return MOTIONS[name]


def view_box(motion: str, size_m: float) -> tuple[list[float], list[float]]:
    """The box a fixed camera frames for every clip of ``motion`` (``Motion.view_box``)."""
    return get_motion(motion).view_box(size_m)


def view_zoom(motion: str, cfg) -> float:
    """How much closer than its ``view_box`` the camera frames ``motion`` under sim settings ``cfg``
    (``Motion.view_zoom``)."""
    return float(get_motion(motion).view_zoom(cfg))


def describe_motions() -> str:
    """A human-readable list (for ``clothgap sim --list-motions``): name and description."""
    return "\n".join(f"{m.name}: {m.description}" for m in MOTIONS.values())
