"""Camera rigs as camera-to-world matrices (OpenGL: the camera looks down -Z, +Y up, +X right).

Rigs are laid out in the y-up frame, where a camera at azimuth 0 sits on +Z looking back at the
target (it sees the front of a `meshes.uv_sphere`, u = 0.5) and azimuth grows counter-clockwise
seen from above; `world_up="+z"` turns the layout by the same axis change as `meshes` and
`environments` ((x, y, z)_y-up -> (x, -z, y)_z-up), and every camera keeps the world's up
direction up in its image.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

__all__ = [
    "up_vector",
    "look_at",
    "fov_to_camera_angle_x",
    "orbit",
    "hemisphere",
    "handheld",
]

#: Below this |sin| between the view direction and up, `look_at` picks another up vector
#: (a camera looking straight down has no defined "up" in its image).
PARALLEL_EPS = 1e-6


def up_vector(world_up: str) -> np.ndarray:
    """The world's up direction as a unit vector."""
    if world_up == "+y":
        return np.array([0.0, 1.0, 0.0])
    if world_up == "+z":
        return np.array([0.0, 0.0, 1.0])
    raise ValueError(f"world_up must be '+y' or '+z', got {world_up!r}")


def _yup_to_world(p, world_up: str) -> np.ndarray:
    p = np.asarray(p, np.float64)
    if world_up == "+y":
        return p
    up_vector(world_up)  # validates
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float], roll_deg: float = 0.0) -> np.ndarray:
    """4x4 camera-to-world of a camera at `eye` looking at `target`, `up` up in its image.

    Columns (OpenGL): z = normalize(eye - target) (the camera looks down -z), x = normalize(up x z)
    (right), y = z x x (up in the image), translation = eye. `roll_deg` turns the camera
    about its viewing axis (counter-clockwise in the image).
    """
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    z = eye - target
    z = z / np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < PARALLEL_EPS:
        alt = np.array([0.0, 0.0, -1.0]) if abs(up[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(alt, z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    if roll_deg:
        c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
        x, y = c * x + s * y, -s * x + c * y
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def fov_to_camera_angle_x(fov_deg: float) -> float:
    """Horizontal field of view in degrees -> the capture's `camera_angle_x` (radians)."""
    return math.radians(fov_deg)


def _position(radius, elevation_deg, azimuth_deg) -> np.ndarray:
    e, a = np.deg2rad(elevation_deg), np.deg2rad(azimuth_deg)
    d = np.stack([np.cos(e) * np.sin(a), np.sin(e) * np.ones_like(a), np.cos(e) * np.cos(a)], axis=-1)
    return np.asarray(radius, np.float64)[..., None] * d


def orbit(
    n: int,
    radius: float = 3.0,
    elevation_deg: float | Sequence[float] = 25.0,
    target: Sequence[float] = (0.0, 0.0, 0.0),
    world_up: str = "+y",
    azimuth_start_deg: float = 0.0,
    azimuth_span_deg: float = 360.0,
) -> np.ndarray:
    """(n, 4, 4) cameras on a circle around `target` (evenly in azimuth; `elevation_deg` may be
    one value or one per camera), all looking at it."""
    full = abs(azimuth_span_deg - 360.0) < 1e-9
    steps = n if full else max(n - 1, 1)
    az = azimuth_start_deg + azimuth_span_deg * np.arange(n) / steps
    el = np.broadcast_to(np.asarray(elevation_deg, np.float64), (n,))
    eyes = _yup_to_world(_position(radius, el, az), world_up) + np.asarray(target, np.float64)
    up = up_vector(world_up)
    return np.stack([look_at(e, target, up) for e in eyes]) if n else np.zeros((0, 4, 4))


def hemisphere(
    n: int,
    radius: float = 3.0,
    target: Sequence[float] = (0.0, 0.0, 0.0),
    world_up: str = "+y",
    min_elevation_deg: float = 15.0,
    max_elevation_deg: float = 75.0,
    rng: Optional[np.random.Generator] = None,
    azimuth_offset_deg: float = 0.0,
) -> np.ndarray:
    """(n, 4, 4) cameras spread evenly over a band of the upper hemisphere (a Fibonacci spiral,
    uniform in solid angle between the two elevations), optionally jittered by `rng`."""
    k = np.arange(n) + 0.5
    s0, s1 = np.sin(np.deg2rad(min_elevation_deg)), np.sin(np.deg2rad(max_elevation_deg))
    sin_el = s0 + (s1 - s0) * k / max(n, 1)
    az = azimuth_offset_deg + np.rad2deg(k * math.pi * (3.0 - math.sqrt(5.0)))  # golden angle
    if rng is not None and n:
        az = az + rng.uniform(-10, 10, n)
        sin_el = np.clip(sin_el + rng.uniform(-0.5, 0.5, n) * (s1 - s0) / n, s0, s1)
    el = np.rad2deg(np.arcsin(sin_el))
    eyes = _yup_to_world(_position(radius, el, az), world_up) + np.asarray(target, np.float64)
    up = up_vector(world_up)
    return np.stack([look_at(e, target, up) for e in eyes]) if n else np.zeros((0, 4, 4))


def handheld(
    n: int,
    rng: np.random.Generator,
    target: Sequence[float] = (0.0, 0.0, 0.0),
    world_up: str = "+y",
    distance: tuple[float, float] = (1.8, 2.6),
    elevation_deg: tuple[float, float] = (40.0, 80.0),
    aim_jitter: float = 0.2,
    roll_deg: float = 8.0,
) -> np.ndarray:
    """(n, 4, 4) a phone walked around an object: azimuths spread evenly with jitter, random
    distance and elevation in the given ranges, aim off the target by up to `aim_jitter` units
    (in the ground plane), and a random roll of up to `roll_deg`. With a `flash`, each frame is
    lit from its own camera."""
    az = 360.0 * (np.arange(n) + rng.uniform(-0.3, 0.3, n)) / max(n, 1)
    el = rng.uniform(*elevation_deg, n)
    dist = rng.uniform(*distance, n)
    roll = rng.uniform(-roll_deg, roll_deg, n)
    aims = np.zeros((n, 3))
    aims[:, [0, 2]] = rng.uniform(-aim_jitter, aim_jitter, (n, 2))
    target = np.asarray(target, np.float64)
    eyes = _yup_to_world(_position(dist, el, az), world_up)
    aims = _yup_to_world(aims, world_up) + target
    up = up_vector(world_up)
    cams = [look_at(eyes[i] + aims[i], aims[i], up, roll_deg=roll[i]) for i in range(n)]
    return np.stack(cams) if n else np.zeros((0, 4, 4))
