"""Lights and surroundings of the cloth, placed relative to the camera's framing.

``fixed`` is the paper's controlled studio: a large soft key light above and to
one side of the camera, a weaker fill from the other side, and a dim uniform
ambient. Light sizes and distances scale with the framing and radiances with
distance squared, so the irradiance on the cloth (and hence the exposure) does
not depend on the clip's size. The key is bright enough that lit, light-coloured
cloth exceeds 1 in linear radiance, so the tone-mapping operators matter.

``random`` draws, per clip, a procedural HDR environment (a soft ceiling-to-
floor gradient with bright window-like patches) and one to three area lights of
random direction, size, intensity and colour temperature (colour-science
converts the temperature to linear sRGB). ``daylight`` is a sun (a directional
light, warmer when low) at a random position plus a procedural clear sky:
Mitsuba's own ``sunsky`` plugin is not used, as with a z-up world its horizon
check and orientation do not behave predictably.

``room_shapes`` puts a floor and two walls around the cloth for
``background = "room"`` (the room is rendered, not composited).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

import colour
import numpy as np

from render.variants import RenderVariant

UP = np.array([0.0, 0.0, 1.0])

# The fixed studio: irradiance each light delivers at the cloth (linear units).
KEY_IRRADIANCE = 4.5
FILL_IRRADIANCE = 1.0
AMBIENT_RADIANCE = 0.25


@dataclass(frozen=True)
class Framing:
    """Where the camera is, what it looks at, and how big the subject is (metres)."""

    target: np.ndarray
    origin: np.ndarray
    distance: float
    radius: float      # half the diagonal of the clip's bounding box
    fov_deg: float
    floor_z: float     # the lowest point the cloth reaches

    @property
    def toward_camera(self) -> np.ndarray:
        """Horizontal unit vector from the target toward the camera."""
        d = self.origin - self.target
        d[2] = 0.0
        return d / max(np.linalg.norm(d), 1e-9)

    @property
    def side(self) -> np.ndarray:
        """Horizontal unit vector to the camera's right."""
        return np.cross(self.toward_camera, UP) * -1.0


def cct_to_rgb(kelvin: float) -> np.ndarray:
    """Linear sRGB colour of a black-body-like source of ``kelvin`` (luminance 1)."""
    xy = colour.temperature.CCT_to_xy(float(kelvin), method="Kang 2002")
    rgb = colour.XYZ_to_RGB(colour.xy_to_XYZ(xy), colourspace="sRGB", apply_cctf_encoding=False)
    return np.clip(np.asarray(rgb, np.float64), 0.0, None)


def _rectangle_light(mi: ModuleType, framing: Framing, direction: np.ndarray, distance: float,
                     half_size: float, irradiance: float, rgb: np.ndarray) -> dict:
    """A square area light at ``distance`` along ``direction`` from the target, facing it.

    Radiance is set so that the light delivers about ``irradiance`` at the target
    (E = L * area / d^2 for a light small against its distance).
    """
    direction = direction / np.linalg.norm(direction)
    position = framing.target + distance * direction
    radiance = irradiance * distance ** 2 / (4.0 * half_size ** 2)
    up = UP if abs(direction @ UP) < 0.99 else framing.toward_camera
    to_world = mi.ScalarTransform4f().look_at(origin=position.tolist(), target=framing.target.tolist(),
                                              up=up.tolist()).scale([half_size, half_size, 1.0])
    return {"type": "rectangle", "to_world": to_world,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": (radiance * rgb).tolist()}}}


def _y_up_to_z_up(mi: ModuleType):
    """Mitsuba's environment emitters have +Y up; the simulator's world has +Z up."""
    return mi.ScalarTransform4f().rotate([1, 0, 0], -90)  # measured: this sends the emitters' zenith to +Z


def emitters(mi: ModuleType, variant: RenderVariant, framing: Framing,
             rng: np.random.Generator) -> tuple[dict, dict]:
    """Scene-dict entries for the variant's lights, and a description for the clip's meta."""
    if variant.lighting == "fixed":
        return _fixed(mi, framing), {"kind": "fixed"}
    if variant.lighting == "random":
        return _random(mi, framing, rng)
    if variant.lighting == "daylight":
        return _daylight(mi, rng)
    raise ValueError(f"unknown lighting {variant.lighting!r}")


def _fixed(mi: ModuleType, framing: Framing) -> dict:
    d = 1.5 * framing.distance
    white = np.ones(3)
    key_dir = framing.toward_camera + 0.7 * (-framing.side) + 1.0 * UP
    fill_dir = framing.toward_camera + 0.9 * framing.side + 0.2 * UP
    return {
        "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": [AMBIENT_RADIANCE] * 3}},
        "key": _rectangle_light(mi, framing, key_dir, d, 0.35 * d, KEY_IRRADIANCE, white),
        "fill": _rectangle_light(mi, framing, fill_dir, d, 0.25 * d, FILL_IRRADIANCE, white),
    }


def _random(mi: ModuleType, framing: Framing, rng: np.random.Generator) -> tuple[dict, dict]:
    env_kelvin = float(rng.uniform(3000, 9000))
    env_level = float(np.exp(rng.uniform(np.log(0.08), np.log(0.6))))
    lights: dict = {"environment": {"type": "envmap", "bitmap": mi.Bitmap(_environment_map(rng, env_kelvin)),
                                    "scale": env_level, "to_world": _y_up_to_z_up(mi)}}
    info: dict = {"kind": "random", "environment": {"kelvin": env_kelvin, "level": env_level}, "lights": []}
    for i in range(int(rng.integers(1, 4))):
        azimuth = np.radians(rng.uniform(-110, 110))  # around the camera's side of the cloth
        elevation = np.radians(rng.uniform(5, 75))
        toward, side = framing.toward_camera, framing.side
        horizontal = np.cos(azimuth) * toward + np.sin(azimuth) * side
        direction = np.cos(elevation) * horizontal + np.sin(elevation) * UP
        distance = float(rng.uniform(1.0, 3.0) * framing.distance)
        half_size = float(rng.uniform(0.05, 0.4) * distance)
        irradiance = float(np.exp(rng.uniform(np.log(1.0), np.log(10.0))))
        kelvin = float(rng.uniform(2700, 7500))
        lights[f"light{i}"] = _rectangle_light(mi, framing, direction, distance, half_size, irradiance,
                                               cct_to_rgb(kelvin))
        info["lights"].append({"direction": direction.tolist(), "distance": distance, "half_size": half_size,
                               "irradiance": irradiance, "kelvin": kelvin})
    return lights, info


def _environment_map(rng: np.random.Generator, kelvin: float, height: int = 32) -> np.ndarray:
    """An equirectangular (height, 2 height, 3) HDR room: bright above, dark below, a few hot window patches."""
    width = 2 * height
    theta = (np.arange(height) + 0.5) / height * np.pi  # 0 at the zenith (+Y in Mitsuba's frame)
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    image = np.empty((height, width, 3))
    image[:] = (0.35 + 0.65 * np.clip(np.cos(theta), 0.0, 1.0) + 0.15)[:, None, None]
    for _ in range(int(rng.integers(1, 4))):
        center_theta, center_phi = rng.uniform(0.3, 1.6), rng.uniform(0, 2 * np.pi)
        size_theta, size_phi = rng.uniform(0.15, 0.5), rng.uniform(0.2, 0.8)
        d_phi = np.angle(np.exp(1j * (phi - center_phi)))
        patch = (np.abs(theta - center_theta)[:, None] < size_theta) & (np.abs(d_phi)[None, :] < size_phi)
        image[patch] += rng.uniform(4.0, 20.0)
    return (image * cct_to_rgb(kelvin)).astype(np.float32)


def _daylight(mi: ModuleType, rng: np.random.Generator) -> tuple[dict, dict]:
    """A sun (directional, warmer when low) and a sky (blue zenith, pale horizon, dim ground) per clip."""
    elevation = float(rng.uniform(10, 70))
    azimuth = float(rng.uniform(0, 360))
    e, a = np.radians(elevation), np.radians(azimuth)
    toward_sun = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    sun_kelvin = 3500.0 + 2500.0 * np.sin(e)  # low sun is reddened by the longer path through air
    sun_irradiance = float(rng.uniform(3.0, 8.0))
    sky_level = float(rng.uniform(0.3, 0.8))
    return ({"sun": {"type": "directional", "direction": (-toward_sun).tolist(),
                     "irradiance": {"type": "rgb", "value": (sun_irradiance * cct_to_rgb(sun_kelvin)).tolist()}},
             "sky": {"type": "envmap", "bitmap": mi.Bitmap(_sky_map()), "scale": sky_level,
                     "to_world": _y_up_to_z_up(mi)}},
            {"kind": "daylight", "sun_elevation_deg": elevation, "sun_azimuth_deg": azimuth,
             "sun_kelvin": sun_kelvin, "sun_irradiance": sun_irradiance, "sky_level": sky_level})


def _sky_map(height: int = 32) -> np.ndarray:
    """An equirectangular clear sky: deep blue at the zenith, pale at the horizon, grey-brown ground below."""
    theta = (np.arange(height) + 0.5) / height * np.pi
    height_above = np.clip(np.cos(theta), 0.0, 1.0)[:, None]
    sky = (1 - height_above) * cct_to_rgb(7000) * 1.2 + height_above * cct_to_rgb(15000)
    ground = np.array([0.35, 0.32, 0.28])
    rows = np.where((np.cos(theta) > 0)[:, None], sky, ground)
    return np.repeat(rows[:, None, :], 2 * height, axis=1).astype(np.float32)


def room_shapes(mi: ModuleType, variant: RenderVariant, framing: Framing, rng: np.random.Generator) -> dict:
    """A floor below the cloth and walls behind and beside it, in diffuse random colours (background="room")."""
    if variant.background != "room":
        return {}
    from render.textures import palette

    wall, side_wall, floor = palette(rng, 3)
    wall = 0.5 * wall + 0.35  # light, muted walls, as in most rooms
    toward, side = framing.toward_camera, framing.side
    big = 6.0 * framing.distance
    back = framing.target - toward * (framing.radius + rng.uniform(0.2, 1.0) * framing.distance)
    back[2] = framing.floor_z + big - 0.5 * framing.radius
    floor_center = framing.target.copy()
    floor_center[2] = framing.floor_z - rng.uniform(0.1, 0.6) * framing.radius
    wall_side = rng.choice([-1.0, 1.0])
    side_center = framing.target + wall_side * side * (framing.radius + rng.uniform(0.5, 1.5) * framing.distance)

    def plane(center: np.ndarray, normal: np.ndarray, rgb: np.ndarray) -> dict:
        up = UP if abs(normal @ UP) < 0.99 else toward
        to_world = mi.ScalarTransform4f().look_at(origin=center.tolist(), target=(center + normal).tolist(),
                                                  up=up.tolist()).scale([big, big, 1.0])
        return {"type": "rectangle", "to_world": to_world,
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": np.clip(rgb, 0, 0.9).tolist()}}}

    return {"room_back": plane(back, toward, wall), "room_floor": plane(floor_center, UP, floor * 0.8),
            "room_side": plane(side_center, -wall_side * side, 0.5 * side_wall + 0.35)}
