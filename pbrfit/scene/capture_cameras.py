"""A frame's camera from ``capture.json``: its camera-to-world matrix (OpenGL axes, checked
affine and finite) and pinhole intrinsics (``camera_angle_x`` or ``fl_x``/``fl_y``, ``cx``/``cy``,
frame before top level; the rules: `pbrfit.scene.capture`'s docstring). Lens distortion is refused."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import CaptureError
from .camera import Camera, camera_axes
from ..io.json_fields import FLOAT32_MAX, field_loc, number_field, positive_field

__all__ = ["camera_to_world", "frame_camera", "fov_focal", "check_distortion", "INTRINSICS_RTOL", "PINHOLE_MODELS",
           "MAX_FOCAL_PIXELS"]

#: When a capture gives both intrinsics forms, fl_x and the fl_x implied by camera_angle_x must
#: agree to this relative tolerance (rounding in the writer), else the capture is refused.
INTRINSICS_RTOL = 1e-2
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
#: The longest focal length in pixels a camera may have: past 1 / float32's epsilon (8.4e6;
#: a field of view under 1.2e-4 radians per thousand pixels) neighbouring pixels' rays are one
#: ray in float32, and every pixel sees the same point (a 2,000 mm lens on a 36 mm, 4,000-pixel
#: sensor has 2.2e5).
MAX_FOCAL_PIXELS = float(1.0 / np.finfo(np.float32).eps)
# The last row of a camera-to-world matrix must be (0, 0, 0, 1) to this tolerance.
_AFFINE_ROW_TOL = 1e-6


def camera_to_world(frame: Mapping, where: str) -> np.ndarray:
    """The frame's ``transform_matrix``: 4 × 4 numbers, finite, within float32's range, with the
    affine last row (0, 0, 0, 1); its rotation part then checked by `pbrfit.scene.camera.camera_axes`."""
    if "transform_matrix" not in frame:
        raise CaptureError(f"{where}: missing key 'transform_matrix'")
    at = field_loc(where, "transform_matrix")
    value = frame["transform_matrix"]
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)) and all(isinstance(row, (list, tuple)) for row in value):
        bad = [v for row in value for v in row if isinstance(v, bool) or not isinstance(v, (int, float))]
        if bad:
            raise CaptureError(f"{at}: expected a 4x4 array of numbers, "
                               f"got {bad[0]!r} in it")
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise CaptureError(f"{at}: expected a 4x4 array of numbers") from None
    if m.shape != (4, 4):
        raise CaptureError(f"{at}: expected shape 4x4, got {'x'.join(map(str, m.shape)) or 'a scalar'}")
    if not np.all(np.isfinite(m)):
        raise CaptureError(f"{at}: non-finite values")
    if np.max(np.abs(m)) > FLOAT32_MAX:
        raise CaptureError(f"{at}: values beyond float32's range (|x| <= 3.4e38)")
    if np.max(np.abs(m[3] - [0.0, 0.0, 0.0, 1.0])) > _AFFINE_ROW_TOL:
        raise CaptureError(f"{at}: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    return camera_axes(m, at)


def frame_camera(top: Mapping, frame: Mapping, c2w: np.ndarray, width: int, height: int, where: str, name: str,
                 image: Path) -> Camera:
    """The frame's pinhole `Camera` for an image of ``width`` × ``height``: intrinsics from the
    frame, else the top level ``top`` (``fl_x`` form, or ``camera_angle_x``), checked against the
    image's size (``w``, ``h``) and against each other when both forms are given."""
    for key in ("w", "h"):
        for obj, owner in ((frame, where), (top, name)):
            if key in obj:
                value = number_field(obj, key, owner, None)
                expected = width if key == "w" else height
                if value != expected:
                    raise CaptureError(
                        f"{field_loc(owner, key)}: says {value:g} but image {image} is {width}x{height} (w x h)"
                    )
                break
    fl_x = positive_field(frame, "fl_x", where)
    frame_fl_x = fl_x is not None  # a frame's own intrinsics override the global ones
    if fl_x is None:
        fl_x = positive_field(top, "fl_x", name)
    fl_y = positive_field(frame, "fl_y", where) or positive_field(top, "fl_y", name)  # with either form of fx
    if fl_x is not None:
        fx, fy = fl_x, fl_y or fl_x
        if "camera_angle_x" in top and not frame_fl_x:  # both global forms (instant-ngp writes both): must agree
            fx_angle = fov_focal(top, "camera_angle_x", width, name)
            if not abs(fl_x - fx_angle) <= INTRINSICS_RTOL * fx_angle:
                raise CaptureError(
                    f"{where}: fl_x {fl_x:g} disagrees with camera_angle_x {top['camera_angle_x']!r} "
                    f"(= fl_x {fx_angle:.6g} at width {width}); give one of the two or make them agree"
                )
    elif "camera_angle_x" in top:
        fx, fy = fov_focal(top, "camera_angle_x", width, name), fl_y
        if fy is None:
            fy = fov_focal(top, "camera_angle_y", height, name) if "camera_angle_y" in top else fx
    else:
        raise CaptureError(f"{where}: no intrinsics: give camera_angle_x, or fl_x (top level or per frame)")
    cx = number_field(frame, "cx", where, None) if "cx" in frame else number_field(top, "cx", name, 0.5 * width)
    cy = number_field(frame, "cy", where, None) if "cy" in frame else number_field(top, "cy", name, 0.5 * height)
    # any finite principal point: the spec gives cx, cy no range, and a crop or tile of a larger
    # image has it outside its own frame
    if max(fx, fy) > MAX_FOCAL_PIXELS:
        raise CaptureError(f"{where}: focal length {max(fx, fy):.3g} pixels: above {MAX_FOCAL_PIXELS:.3g}, every "
                           "pixel's ray is the same in float32 (is the field of view, or fl_x, in the right units?)")
    try:
        return Camera(c2w, fx, fy, cx, cy, width, height)
    except CaptureError as err:
        raise CaptureError(f"{where}: {err}") from None


def fov_focal(top, key: str, size: int, name: str) -> float:
    """The focal length in pixels of the field of view ``top[key]`` (radians, in (0, pi)) across
    `size` pixels: ``size / (2 tan(angle / 2))``."""
    angle = number_field(top, key, name, None)
    if not 0.0 < angle < math.pi:
        raise CaptureError(f"{name}: {key}: must be in (0, pi) radians, got {angle!r}")
    return 0.5 * size / math.tan(0.5 * angle)


def check_distortion(obj: Mapping, where: str) -> None:
    for key in _DISTORTION_KEYS:
        if key in obj and number_field(obj, key, where, None) != 0.0:
            raise CaptureError(f"{field_loc(where, key)}: lens distortion is not supported; undistort the images first")
