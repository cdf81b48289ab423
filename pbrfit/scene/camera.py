"""Cameras as the capture spec has them: OpenGL-style camera-to-world matrices (the camera looks
down its -Z axis, +Y up, +X right) with pinhole intrinsics; pixel (i, j) (row i from the top,
column j) has its centre at x = j + 0.5, y = i + 0.5, and its camera-space ray is
((x - cx)/fx, -(y - cy)/fy, -1). `camera_axes` checks a matrix's axes."""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float

from ..errors import CaptureError

__all__ = ["Camera", "camera_axes", "pixel_offsets", "sample_camera", "ORTHONORMAL_TOL", "UNIT_TOL", "AXIS_FLOOR"]


#: The largest |cos| between two camera axes (columns of the rotation, normalised) taken as perpendicular.
ORTHONORMAL_TOL = 1e-3
#: Camera axes whose lengths are within this of 1 are taken as they are (not renormalised).
UNIT_TOL = 1e-9
#: A camera axis (rotation column) shorter than this is zero: it has no direction to normalise.
AXIS_FLOOR = 1e-12


def camera_axes(c2w: Float[np.ndarray, "4 4"], label: str = "camera: transform") -> Float[np.ndarray, "4 4"]:
    """A camera-to-world matrix with unit axes: a scale on the axes (a scaled camera object in
    Blender) changes no ray and is taken out; axes that are not perpendicular (a shear), zero or
    mirrored (a left-handed frame) are no camera: `CaptureError`, worded with ``label``."""
    m = np.asarray(c2w, np.float64)
    norms = np.linalg.norm(m[:3, :3], axis=0)
    if np.min(norms) < AXIS_FLOOR:
        raise CaptureError(f"{label}: a camera axis (rotation column) is zero")
    axes = m[:3, :3] / norms
    gram = axes.T @ axes
    if np.max(np.abs(gram - np.eye(3))) > ORTHONORMAL_TOL:
        raise CaptureError(f"{label}: the camera's axes (rotation columns) are not "
                           f"perpendicular (largest |cos| between two {np.max(np.abs(gram - np.eye(3))):.3g})")
    if np.linalg.det(axes) < 0:
        raise CaptureError(f"{label}: the camera's axes are mirrored (a left-handed "
                           "frame); expected +X right, +Y up, looking down -Z")
    if np.max(np.abs(norms - 1.0)) > UNIT_TOL:  # (a unit frame as given: its values unchanged)
        m = m.copy()
        m[:3, :3] = axes
    return m


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: camera-to-world matrix and intrinsics in pixels.

    OpenGL convention (looks down -Z, +Y up, +X right); pixel centres at (j + 0.5, i + 0.5),
    row 0 at the top. Equality and hashing compare values. ``c2w``'s axes are scaled to unit
    length; zero, sheared or mirrored axes are refused (`camera_axes`).
    """

    c2w: Float[np.ndarray, "4 4"]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        c2w = np.array(self.c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise CaptureError(f"camera: transform must be a finite 4x4 matrix, got shape {c2w.shape}")
        c2w = np.array(camera_axes(c2w), dtype=np.float64)  # unit, perpendicular, right-handed axes
        c2w.setflags(write=False)
        object.__setattr__(self, "c2w", c2w)
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or (name in ("fx", "fy") and value <= 0):
                raise CaptureError(f"camera: {name} must be finite{' and > 0' if name in ('fx', 'fy') else ''}, got {value}")
            object.__setattr__(self, name, value)
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or int(value) <= 0:
                raise CaptureError(f"camera: {name} must be a positive integer, got {value}")
            object.__setattr__(self, name, int(value))

    @classmethod
    def from_fov(cls, c2w, camera_angle_x: float, width: int, height: int) -> "Camera":
        """Square pixels, principal point at the image centre: fx = fy = W / (2 tan(angle_x / 2))."""
        if not 0.0 < float(camera_angle_x) < np.pi:
            raise CaptureError(f"camera: camera_angle_x must be in (0, pi), got {camera_angle_x}")
        f = 0.5 * width / np.tan(0.5 * float(camera_angle_x))
        return cls(c2w, f, f, 0.5 * width, 0.5 * height, width, height)

    def _params(self) -> tuple:
        return (self.c2w.tobytes(), self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def __eq__(self, other):
        return isinstance(other, Camera) and self._params() == other._params()

    def __hash__(self):
        return hash(self._params())

    @property
    def center(self) -> Float[np.ndarray, "3"]:
        """Camera position in world space."""
        return self.c2w[:3, 3].copy()

    def rays(self) -> tuple[Float[np.ndarray, "H W 3"], Float[np.ndarray, "H W 3"]]:
        """World-space origins and unit directions of the rays through every pixel centre."""
        x = np.arange(self.width, dtype=np.float64) + 0.5
        y = np.arange(self.height, dtype=np.float64) + 0.5
        xx, yy = np.meshgrid(x, y)  # (H, W), row index = y
        d_cam = np.stack([(xx - self.cx) / self.fx, -(yy - self.cy) / self.fy, -np.ones_like(xx)], -1)
        world = d_cam @ self.c2w[:3, :3].T
        norm = np.linalg.norm(world, axis=-1, keepdims=True)  # >= 1 (camera-space z is -1), or not finite
        with np.errstate(invalid="ignore"):  # a focal length so small that a ray is infinite: no ray (zero)
            directions = np.where(norm > 0, world / np.where(norm > 0, norm, 1.0), 0.0)
        origins = np.broadcast_to(self.center, directions.shape).copy()
        return origins, directions

    def to_camera(self, points: Float[np.ndarray, "*b 3"]) -> Float[np.ndarray, "*b 3"]:
        """World points in camera space (the camera looks down -Z)."""
        w2c = np.linalg.inv(self.c2w)
        p = np.asarray(points, dtype=np.float64)
        return p @ w2c[:3, :3].T + w2c[:3, 3]

    def project(self, points: Float[np.ndarray, "*b 3"]) -> Float[np.ndarray, "*b 2"]:
        """Continuous pixel coordinates (x = column, y = row; centres at k + 0.5) of world points.

        x = cx + fx X / (-Z), y = cy - fy Y / (-Z) for camera-space (X, Y, Z). Points on or
        behind the camera plane (Z >= 0) project to NaN.
        """
        pc = self.to_camera(points)
        depth = -pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(depth > 0, 1.0 / depth, np.nan)
        return np.stack([self.cx + self.fx * pc[..., 0] * inv, self.cy - self.fy * pc[..., 1] * inv], -1)


def pixel_offsets(n: int) -> np.ndarray:
    """(n², 2) sample positions (x right, y down) inside a pixel, in pixel units from its corner:
    the centres of an n × n grid of sub-pixels, row by row (n = 1: the pixel centre)."""
    c = (np.arange(n, dtype=np.float64) + 0.5) / n
    yy, xx = np.meshgrid(c, c, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], -1)


def sample_camera(camera, offset):
    """``camera`` with its principal point moved so that its pixel centres fall at ``offset``
    (x, y, one of `pixel_offsets`) of the original's pixels: a ray through pixel centre j + 0.5
    of a camera whose principal point moved by 0.5 - offset passes through j + offset."""
    ox, oy = offset
    return dataclasses.replace(camera, cx=camera.cx + 0.5 - ox, cy=camera.cy + 0.5 - oy)
