"""Procedural HDR environments (equirectangular, linear radiance).

Images are laid out as the capture spec says, in the *environment frame* (up = +Y): the top row
looks up, the image centre looks along -Z and u grows with azimuth atan2(x, -z):
``u = 0.5 + atan2(x, -z) / (2 pi)``, ``v = acos(y) / pi``, pixel (i, j) centred at
((j + .5)/W, (i + .5)/H). A capture with ``world_up = "+z"`` reads the same image through the
Blender -> glTF axis change (x, y, z) -> (x, z, -y); `world_to_env` and `env_to_world` are that
map, so a sun placed with `direction_from_angles` in the environment frame is found in world
space with `env_to_world`.

The sky is a simple analytic one (zenith-to-horizon gradient, a brightening around the sun, a
sun disk with a soft edge, a ground below the horizon); the studio is a dark room with soft
rectangular light boxes. Both are smooth at the pixel scale so prefiltering does not alias.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

__all__ = [
    "Softbox",
    "DEFAULT_SOFTBOXES",
    "equirect_directions",
    "direction_to_uv",
    "direction_from_angles",
    "world_to_env",
    "env_to_world",
    "sky",
    "studio",
    "constant",
    "write_environment",
]

#: Width of the smooth edges (sun disk, horizon, softbox borders) in pixels of the equirect:
#: a step narrower than ~2 pixels aliases in the prefiltered mip stack.
EDGE_PIXELS = 2.0


def equirect_directions(width: int, height: int) -> np.ndarray:
    """(H, W, 3) unit directions (environment frame) through the pixel centres."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    phi = (u - 0.5) * 2.0 * np.pi  # azimuth atan2(x, -z)
    theta = v * np.pi  # polar angle from +Y
    phi, theta = np.meshgrid(phi, theta, indexing="xy")
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), -s * np.cos(phi)], axis=-1)


def direction_to_uv(d) -> np.ndarray:
    """(..., 2) equirect uv of unit directions (environment frame); inverse of `equirect_directions`."""
    d = np.asarray(d, np.float64)
    u = 0.5 + np.arctan2(d[..., 0], -d[..., 2]) / (2.0 * np.pi)
    v = np.arccos(np.clip(d[..., 1], -1.0, 1.0)) / np.pi
    return np.stack([u, v], axis=-1)


def direction_from_angles(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit direction (environment frame) at an elevation above the horizon and an azimuth
    (0 = the image centre, -Z; 90 = +X, a quarter of the image to the right)."""
    e, a = np.deg2rad(elevation_deg), np.deg2rad(azimuth_deg)
    return np.array([np.cos(e) * np.sin(a), np.sin(e), -np.cos(e) * np.cos(a)])


def world_to_env(d, world_up: str = "+y") -> np.ndarray:
    """World directions to the environment frame: identity for +y, (x, y, z) -> (x, z, -y) for +z."""
    d = np.asarray(d, np.float64)
    if world_up == "+y":
        return d
    if world_up == "+z":
        return np.stack([d[..., 0], d[..., 2], -d[..., 1]], axis=-1)
    raise ValueError(f"world_up must be '+y' or '+z', got {world_up!r}")


def env_to_world(d, world_up: str = "+y") -> np.ndarray:
    """Inverse of `world_to_env`: (x, y, z) -> (x, -z, y) for +z."""
    d = np.asarray(d, np.float64)
    if world_up == "+y":
        return d
    if world_up == "+z":
        return np.stack([d[..., 0], -d[..., 2], d[..., 1]], axis=-1)
    raise ValueError(f"world_up must be '+y' or '+z', got {world_up!r}")


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def sky(
    width: int = 256,
    height: int = 128,
    sun_elevation_deg: float = 40.0,
    sun_azimuth_deg: float = 30.0,
    sun_radius_deg: float = 3.0,
    sun_radiance: Sequence[float] = (220.0, 200.0, 170.0),
    zenith: Sequence[float] = (0.25, 0.45, 0.95),
    horizon: Sequence[float] = (0.9, 0.95, 1.0),
    ground: Sequence[float] = (0.25, 0.21, 0.17),
    intensity: float = 1.0,
) -> np.ndarray:
    """(H, W, 3) float32 sky: gradient, glow around the sun, sun disk, ground.

    Sky radiance ``L(e) = horizon + (zenith - horizon) sqrt(sin e)`` for elevation e, times
    ``1 + 1.5 exp(-gamma / 0.35)`` with gamma the angle to the sun (a crude forward-scattering
    glow); the sun disk has radius `sun_radius_deg` and a soft edge; below the horizon a flat
    `ground` colour, blended over `EDGE_PIXELS`.
    """
    d = equirect_directions(width, height)
    sun = direction_from_angles(sun_elevation_deg, sun_azimuth_deg)
    elev = np.arcsin(np.clip(d[..., 1], -1, 1))
    gamma = np.arccos(np.clip(d @ sun, -1, 1))
    pixel = np.pi / height
    zenith, horizon, ground = (np.asarray(c, np.float64) for c in (zenith, horizon, ground))
    t = np.sqrt(np.clip(np.sin(elev), 0.0, 1.0))[..., None]
    sky_l = (horizon + (zenith - horizon) * t) * (1.0 + 1.5 * np.exp(-gamma / 0.35))[..., None]
    ground_l = ground * (0.7 + 0.3 * np.exp(elev / 0.2))[..., None]  # a little brighter near the horizon
    above = _smoothstep(-EDGE_PIXELS * pixel, EDGE_PIXELS * pixel, elev)[..., None]
    radiance = above * sky_l + (1 - above) * ground_l
    r = np.deg2rad(sun_radius_deg)
    disk = 1.0 - _smoothstep(r - EDGE_PIXELS * pixel / 2, r + EDGE_PIXELS * pixel / 2, gamma)
    radiance = radiance + disk[..., None] * np.asarray(sun_radiance, np.float64) * above
    return (intensity * radiance).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Softbox:
    """A rectangular area light of the studio, in angles (environment frame)."""

    elevation_deg: float
    azimuth_deg: float
    width_deg: float
    height_deg: float
    radiance: tuple[float, float, float]


#: Key light front-left, fill right-behind, a top light: the classic three-box studio.
DEFAULT_SOFTBOXES = (
    Softbox(elevation_deg=30.0, azimuth_deg=-40.0, width_deg=40.0, height_deg=30.0, radiance=(8.0, 8.0, 7.6)),
    Softbox(elevation_deg=15.0, azimuth_deg=120.0, width_deg=30.0, height_deg=30.0, radiance=(2.5, 2.6, 3.0)),
    Softbox(elevation_deg=75.0, azimuth_deg=0.0, width_deg=40.0, height_deg=25.0, radiance=(4.0, 4.0, 4.0)),
)


def studio(
    width: int = 256,
    height: int = 128,
    softboxes: Sequence[Softbox] = DEFAULT_SOFTBOXES,
    wall: Sequence[float] = (0.06, 0.06, 0.065),
    floor: Sequence[float] = (0.12, 0.115, 0.11),
    intensity: float = 1.0,
) -> np.ndarray:
    """(H, W, 3) float32 studio: dark walls, a lighter floor, soft-edged rectangular boxes.

    A box covers the directions whose azimuth and elevation lie within half its width and
    height of its centre (measured on the great circle through the centre, so boxes keep their
    size near the poles), with edges smoothed over `EDGE_PIXELS`.
    """
    d = equirect_directions(width, height)
    elev = np.arcsin(np.clip(d[..., 1], -1, 1))
    pixel = np.pi / height
    above = _smoothstep(-EDGE_PIXELS * pixel, EDGE_PIXELS * pixel, elev)[..., None]
    radiance = above * np.asarray(wall, np.float64) + (1 - above) * np.asarray(floor, np.float64)
    for box in softboxes:
        c = direction_from_angles(box.elevation_deg, box.azimuth_deg)
        right = direction_from_angles(0.0, box.azimuth_deg + 90.0)
        up = np.cross(right, c)
        x = np.arctan2(d @ right, d @ c)  # angle along the box's horizontal axis
        y = np.arcsin(np.clip(d @ up, -1, 1))  # angle along its vertical axis
        hw, hh = np.deg2rad(box.width_deg) / 2, np.deg2rad(box.height_deg) / 2
        e = EDGE_PIXELS * pixel / 2
        wx = 1.0 - _smoothstep(hw - e, hw + e, np.abs(x))
        wy = 1.0 - _smoothstep(hh - e, hh + e, np.abs(y))
        front = (d @ c > 0)
        weight = (wx * wy * front)[..., None]
        radiance = (1 - weight) * radiance + weight * np.asarray(box.radiance, np.float64)
    return (intensity * radiance).astype(np.float32)


def constant(width: int = 32, height: int = 16, radiance: Sequence[float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """(H, W, 3) float32 uniform environment (a furnace test)."""
    return np.broadcast_to(np.asarray(radiance, np.float32), (height, width, 3)).copy()


def write_environment(path, radiance: np.ndarray) -> None:
    """Write an environment as a float32 RGB EXR (atomically, through `pbrfit.io.images`)."""
    from pbrfit.io.images import write_image

    write_image(path, np.asarray(radiance, np.float32), "float")
