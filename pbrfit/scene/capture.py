"""Captures: loading and validating ``capture.json`` (spec: ``pbrfit-capture/1``).

`load_capture` turns a capture folder into a `Capture`: the mesh, one `Frame` per image (pixels
in linear float32, mask, camera, lights, exposure), the environment and the image encoding.
Every problem with the input raises `pbrfit.errors.CaptureError` with one line naming the file or
key and what is wrong; every field is checked by `pbrfit.io.json_fields`. A frame's camera comes
from its intrinsics and ``transform_matrix`` (`frame_camera`), the frame from its image, mask,
lights and exposure (`load_frame`), and image paths as NeRF writes them (`resolve_image_path`).

Rules pinned here (tests in ``tests/scene/test_scene.py``):

* Input path: a folder (its ``capture.json``, else its ``transforms.json``) or a ``.json`` file.
  ``format`` must be ``"pbrfit-capture/1"``; it may be absent only in a NeRF-style file whose
  name starts with ``transforms`` (``transforms.json``, ``transforms_train.json``), which then
  needs a ``mesh`` key like any capture.
* Keys: objects pbrfit owns (``lights[]``, ``flash``, ``environment``, ``images``) reject any
  key they do not define. The top level and ``frames[]`` accept pbrfit's keys plus the NeRF /
  instant-ngp / nerfstudio keys listed in `NERF_TOP_LEVEL_KEYS` and `NERF_FRAME_KEYS` and reject
  anything else. ``extras`` (glTF's name for application data) is accepted and ignored at the
  top level and in every object. Lens distortion (nonzero ``k1`` ... ``p2``), ``is_fisheye``
  and non-pinhole ``camera_model`` are refused: pbrfit's cameras are pinholes.
* Intrinsics, per frame: ``fl_x`` (frame, else top level) selects the pinhole form: ``fl_y``
  defaults to ``fl_x``; otherwise ``camera_angle_x`` gives ``fx = W / (2 tan(angle_x / 2))``, and
  ``fy`` is a given ``fl_y`` (frame, else top level), else from ``camera_angle_y`` when present,
  else ``fy = fx``. ``cx``, ``cy`` (frame, else top
  level, else ``W/2``, ``H/2``) apply to either form. ``w``, ``h``, when given, must equal the
  image size, and the principal point must lie inside the image.
* Paths are relative to the folder of the json file. A path whose suffix is not a known image
  extension (NeRF's ``./train/r_0``) is tried with ``.png`` appended, then ``.exr``, then as
  written; a path with an image suffix is used as written. Same rule for ``mask_path``.
* Color space: ``images.color_space`` when given, else by file: EXR and HDR linear, PNG and
  JPEG sRGB, other files sRGB when 8-bit integer, linear otherwise (16-bit TIFF), frame by
  frame. sRGB files are decoded to linear with `pbrfit.physics.color.srgb_to_linear_host`.
  ``Capture.color_space`` is the space a fit takes residuals in: the frames' common one, or
  linear when they mix (the sRGB frames are then compared after decoding).
* Exposure: a frame's effective EV is ``images.exposure + frames[].exposure`` (both default 0).
* Masks: ``mask_path`` (nonzero in its first channel, and in its alpha when it has one = use),
  else the image's alpha channel (nonzero = use), else every pixel (and a fit leaves out the
  mesh's silhouette pixels, which may hold background: `pbrfit.render.views.capture_views`). Color
  stored premultiplied by alpha (`pbrfit.io.images.ImageInfo.associated_alpha`: EXR, and TIFF unless
  the file says unassociated) is divided by it where 0 < alpha < 1, so a partly covered edge pixel holds the surface's color rather than
  a darkened one. Pixels with a NaN or inf channel are set to 0 and, within the mask, marked
  (``Frame.nonfinite``): a fit that would read one (the mesh covers it) refuses the capture.
  ``saturated`` marks pixels of integer (LDR) files with any color channel at the maximum code.
* Lights of a frame: the global ``lights``, then the frame's ``lights``, then the ``flash`` as a
  point light at the camera centre plus ``offset`` (camera space).
* Mesh: `pbrfit.scene.mesh.load_mesh` (uv in glTF orientation for every format).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from ..errors import CaptureError
from ..io.images import _LDR_MAX, ImageInfo, color_channels, data_window_mask, read_image, read_image_info, srgb_decoded
from ..io.json_fields import (FLOAT32_MAX, JSONError, check_keys, field_loc, number_field, object_field, parse_json,
                              positive_field, string_field, triple_field, without_nulls)
from ..io.lights import color_and_intensity, light_from_json
from ..physics.lights import Light, flash_light
from .camera import Camera, camera_axes
from .mesh import load_mesh
from ..physics.color import COLOR_SPACES, TONEMAPS

__all__ = [
    "CAPTURE_FORMAT",
    "WORLD_UPS",
    "PBRFIT_TOP_LEVEL_KEYS",
    "NERF_TOP_LEVEL_KEYS",
    "PBRFIT_FRAME_KEYS",
    "NERF_FRAME_KEYS",
    "IMAGE_SUFFIXES",
    "EnvironmentSpec",
    "Frame",
    "Capture",
    "load_capture",
    "resolve_image_path",
    "load_frame",
    "MAX_EXPOSURE",
    "camera_to_world",
    "frame_camera",
    "fov_focal",
    "check_distortion",
    "INTRINSICS_RTOL",
    "PINHOLE_MODELS",
    "MAX_FOCAL_PIXELS",
]


# --- cameras --------------------------------------------------------------------------------


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


# --- frames ---------------------------------------------------------------------------------


PBRFIT_FRAME_KEYS = ("file_path", "transform_matrix", "mask_path", "lights", "exposure",
                     "fl_x", "fl_y", "cx", "cy", "extras")  # fmt: skip
NERF_FRAME_KEYS = ("w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "rotation", "colmap_im_id",
                   "sharpness", "depth_path", "depth_file_path", "time")  # fmt: skip

#: suffixes taken as "has an extension"; any other path is tried with .png, then .exr appended
IMAGE_SUFFIXES = (".exr", ".hdr", ".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".tga")
_TRY_SUFFIXES = (".png", ".exr")
_LINEAR_FORMATS = ("openexr", "hdr")
_SRGB_FORMATS = ("png", "jpeg")
#: The largest |exposure| in EV a frame may have: 2^64 ≈ 1.8e19 leaves float32 room for the radiance.
MAX_EXPOSURE = 64.0


@dataclass
class Frame:
    """One view.

    Attributes:
        file_path: the image file (resolved).
        image: (H, W, 3) float32 linear RGB (sRGB-decoded when the frame is sRGB); 0 where the
            file held NaN or inf.
        mask: (H, W) bool, pixels to use (mask file, alpha, or all).
        saturated: (H, W) bool, LDR pixels with a color channel at the maximum code.
        nonfinite: (H, W) bool, pixels of the mask whose file values were NaN or inf (set to 0
            in ``image``): a fit that would read one refuses the capture
            (`pbrfit.fitting.observations.observations_from_capture`); off the mesh they do no harm.
        mask_source: where ``mask`` came from: ``"file"`` (mask_path), ``"alpha"``, or ``"none"``
            (every pixel; a fit then leaves out the mesh's silhouette pixels, see
            `pbrfit.render.views.capture_views`).
        camera: `pbrfit.scene.camera.Camera`.
        lights: global lights + the frame's lights + the flash (as a point light).
        exposure: effective EV (``images.exposure + frames[i].exposure``).
        color_space: how the file was encoded (``"linear"`` or ``"srgb"``).
        info: the file's `pbrfit.io.images.ImageInfo` (type, bit depth, alpha channel).
        index: position in ``frames``.
    """

    file_path: Path
    image: np.ndarray
    mask: np.ndarray
    saturated: np.ndarray
    camera: Camera
    lights: tuple[Light, ...]
    exposure: float
    color_space: str = "linear"
    info: Optional[ImageInfo] = None
    index: int = 0
    nonfinite: Optional[np.ndarray] = None
    mask_source: str = "none"


def resolve_image_path(root: Path, rel: str, where: str) -> Path:
    """Resolve an image path from capture.json (see the extension-less rule in the module doc)."""
    path = root / rel
    if path.suffix.lower() in IMAGE_SUFFIXES:
        candidates = [path]
    else:
        candidates = [path.with_name(path.name + s) for s in _TRY_SUFFIXES] + [path]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    tried = " or ".join(str(c) for c in candidates)
    raise CaptureError(f"{where}: image file not found: {tried}")


def _default_color_space(info: ImageInfo) -> str:
    if info.file_format in _LINEAR_FORMATS:
        return "linear"
    if info.file_format in _SRGB_FORMATS:
        return "srgb"
    return "srgb" if (info.is_ldr and info.bits == 8) else "linear"


def _rgb(pixels: np.ndarray, info: ImageInfo, where: str) -> np.ndarray:
    color = color_channels(info, where)
    if len(color) == 3:
        return pixels[..., color]
    if len(color) == 1:
        return np.repeat(pixels[..., color], 3, axis=-1)
    raise CaptureError(f"{where}: image {info.path} has {info.channels} channels; expected gray, RGB or RGBA")


def _nonzero(values: np.ndarray) -> np.ndarray:
    """A mask's "nonzero = use the pixel" (negative values included; NaN is not a value)."""
    return (values != 0) & ~np.isnan(values)


def load_frame(raw, frame_raw, i, root, name, color_space_override, base_exposure, global_lights, flash) -> Frame:
    """Validate and load ``frames[i]`` (see the module docstring for the rules)."""
    where = f"{name}: frames[{i}]"
    frame_raw = object_field(frame_raw, where)
    check_keys(frame_raw, PBRFIT_FRAME_KEYS + NERF_FRAME_KEYS, where, "a frame")
    check_distortion(frame_raw, where)
    if "file_path" not in frame_raw:
        raise CaptureError(f"{where}: missing key 'file_path'")
    c2w = camera_to_world(frame_raw, where)
    file_path = resolve_image_path(root, string_field(frame_raw, "file_path", where), f"{where}.file_path")
    pixels, info = read_image(file_path, f"{where}.file_path")
    height, width = pixels.shape[:2]
    camera = frame_camera(raw, frame_raw, c2w, width, height, where, name, file_path)

    rgb = _rgb(pixels, info, f"{where}.file_path")
    overflow = np.zeros((height, width), bool)
    if info.associated_alpha:  # premultiplied (EXR, TIFF): partly covered pixels get the surface's color back
        alpha = pixels[..., info.alpha_channel : info.alpha_channel + 1]
        # wherever alpha is nonzero, the spec's "nonzero = use the pixel" (an integer file's colour
        # under a small alpha comes back in few codes: its quantisation is the file's)
        partial = (alpha > 0.0) & (alpha < 1.0)
        with np.errstate(over="ignore"):
            divided = np.where(partial, rgb / np.where(partial, alpha, 1.0), rgb).astype(np.float32)
        # a colour too bright for float32 once divided by a tiny alpha: not used (the file holds no NaN)
        overflow = np.all(np.isfinite(rgb), axis=-1) & ~np.all(np.isfinite(divided), axis=-1)
        rgb = np.where(overflow[..., None], 0.0, divided).astype(np.float32)
    color_space = color_space_override or _default_color_space(info)
    saturated = np.zeros((height, width), bool)
    if info.is_ldr:
        code_max = float(_LDR_MAX[info.format])
        saturated = np.any(rgb >= (code_max - 0.5) / code_max, axis=-1)

    if "mask_path" in frame_raw:
        mask_file = resolve_image_path(root, string_field(frame_raw, "mask_path", where), f"{where}.mask_path")
        mask_pixels, mask_info = read_image(mask_file, f"{where}.mask_path")
        if mask_pixels.shape[:2] != (height, width):
            raise CaptureError(
                f"{field_loc(where, 'mask_path')}: mask {mask_file} is {mask_pixels.shape[1]}x{mask_pixels.shape[0]}, "
                f"image is {width}x{height}"
            )
        mask = _nonzero(mask_pixels[..., 0])
        if mask_info.alpha_channel is not None and mask_info.alpha_channel != 0:  # an RGBA mask: alpha too
            mask &= _nonzero(mask_pixels[..., mask_info.alpha_channel])
        mask_source = "file"
    elif info.alpha_channel is not None:
        mask = _nonzero(pixels[..., info.alpha_channel])
        mask_source = "alpha"
    else:
        mask_source = "none"
        mask = np.ones((height, width), bool)
    mask &= data_window_mask(info)  # a cropped OpenEXR: the display window's empty part is not observed
    mask &= ~overflow

    bad = ~np.all(np.isfinite(rgb), axis=-1)
    nonfinite = bad & mask  # an error only if the mesh covers one (known after ray casting)
    if bad.any():
        rgb = np.where(bad[..., None], 0.0, rgb).astype(np.float32)
    image = srgb_decoded(rgb) if color_space == "srgb" else np.ascontiguousarray(rgb, dtype=np.float32)

    frame_lights_raw = frame_raw.get("lights", [])
    if not isinstance(frame_lights_raw, list):
        raise CaptureError(f"{field_loc(where, 'lights')}: expected a list of lights")
    lights = global_lights + tuple(
        light_from_json(d, f"{where}.lights[{k}]") for k, d in enumerate(frame_lights_raw)
    )
    if flash is not None:
        lights = lights + (flash_light(c2w, *flash),)
    exposure = base_exposure + number_field(frame_raw, "exposure", where, 0.0)
    if abs(exposure) > MAX_EXPOSURE:  # 2^EV times a radiance would leave float32's range
        raise CaptureError(f"{field_loc(where, 'exposure')}: exposure {exposure:g} EV (with images.exposure) is beyond "
                           f"±{MAX_EXPOSURE:g} EV")
    return Frame(
        file_path=file_path, image=image, mask=mask, saturated=saturated, nonfinite=nonfinite,
        mask_source=mask_source, camera=camera,
        lights=lights, exposure=exposure, color_space=color_space, info=info, index=i,
    )  # fmt: skip


# --- the capture ----------------------------------------------------------------------------


CAPTURE_FORMAT = "pbrfit-capture/1"
WORLD_UPS = ("+y", "+z")
PBRFIT_TOP_LEVEL_KEYS = (
    "format", "mesh", "world_up", "camera_angle_x", "fl_x", "fl_y", "cx", "cy",
    "frames", "lights", "flash", "environment", "images", "extras",
)  # fmt: skip
#: NeRF (Blender), instant-ngp and nerfstudio keys tolerated at the top level. ``camera_angle_y``,
#: ``w``, ``h`` are read; the distortion keys must be 0; the rest is ignored.
NERF_TOP_LEVEL_KEYS = (
    "camera_angle_y", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "is_fisheye", "camera_model",
    "aabb_scale", "scale", "offset", "applied_transform", "applied_scale", "ply_file_path",
    "integer_depth_scale", "enable_depth_loading", "sharpen", "up", "aabb", "render_aabb",
    "n_extra_learnable_dims", "white_transparent", "black_transparent", "orientation_override",
    "fisheye_crop_radius",
)  # fmt: skip
_IMAGES_KEYS = ("color_space", "tonemap", "exposure", "extras")
_FLASH_KEYS = ("color", "intensity", "offset", "extras")
_ENVIRONMENT_KEYS = ("file", "intensity", "rotation_deg", "extras")


@dataclass(frozen=True)
class EnvironmentSpec:
    """The ``environment`` object: an equirect file (resolved), its scale and rotation about up;
    ``where`` names where the file was given, for errors found when its pixels are read."""

    file: Path
    intensity: float = 1.0
    rotation_deg: float = 0.0
    where: str = "environment"


@dataclass
class Capture:
    """A loaded capture; see the module docstring for the rules.

    ``mesh.visual.uv`` is in glTF orientation (or absent when loaded with ``require_uv=False``
    from a mesh without texture coordinates).
    """

    root: Path
    mesh: Any  # trimesh.Trimesh
    mesh_path: Path
    world_up: str
    frames: list[Frame]
    environment: Optional[EnvironmentSpec]
    color_space: str
    tonemap: str
    truth_dir: Optional[Path]
    raw: dict
    json_path: Optional[Path] = None
    lights: tuple[Light, ...] = ()
    exposure: float = 0.0

    @property
    def uv(self) -> Optional[np.ndarray]:
        """(V, 2) texture coordinates in glTF orientation, or None."""
        return getattr(self.mesh.visual, "uv", None)


# --- paths ---------------------------------------------------------------------------------------
def _json_path(path: Path) -> Path:
    if path.is_dir():
        for name in ("capture.json", "transforms.json"):
            if (path / name).is_file():
                return path / name
        raise CaptureError(f"{path}: no capture.json (or transforms.json) in this folder")
    if not path.exists():
        raise CaptureError(f"{path}: capture not found")
    return path


def _read_json(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise CaptureError(f"{path}: not a capture.json: not UTF-8 text (a binary file?)") from None
    except OSError as err:
        raise CaptureError(f"{path}: cannot read ({type(err).__name__}: {err})".splitlines()[0]) from None
    try:
        raw = parse_json(text)
    except JSONError as err:
        raise CaptureError(f"{path}: {err}") from None
    if not isinstance(raw, dict):
        raise CaptureError(f"{path}: expected a JSON object at the top level, got {type(raw).__name__}")
    return raw


def _parse_flash(raw: Mapping, name: str) -> Optional[tuple[np.ndarray, float, np.ndarray]]:
    """``flash`` -> (color, intensity, offset), or None."""
    if raw.get("flash") is None:
        return None
    where = f"{name}: flash"
    flash = object_field(raw["flash"], where)
    check_keys(flash, _FLASH_KEYS, where, "flash")
    color, intensity = color_and_intensity(flash, where)
    return color, intensity, triple_field(flash, "offset", where, (0.0, 0.0, 0.0))


def _parse_environment(raw: Mapping, name: str, root: Path) -> Optional[EnvironmentSpec]:
    if raw.get("environment") is None:
        return None
    where = f"{name}: environment"
    env = object_field(raw["environment"], where)
    check_keys(env, _ENVIRONMENT_KEYS, where, "environment")
    if "file" not in env:
        raise CaptureError(f"{where}: missing key 'file'")
    env_file = root / string_field(env, "file", where)
    read_image_info(env_file, f"{where}.file")  # exists and is an image (header only)
    intensity = number_field(env, "intensity", where, 1.0)
    if intensity < 0:
        raise CaptureError(f"{where}.intensity: negative intensity {intensity!r}")
    return EnvironmentSpec(env_file, intensity, number_field(env, "rotation_deg", where, 0.0), f"{where}.file")


# --- the loader ----------------------------------------------------------------------------------
def load_capture(path: str | Path, require_uv: bool = True) -> Capture:
    """Load and validate a capture folder, ``capture.json``, or NeRF-style ``transforms*.json``.

    Returns a `Capture`; raises `CaptureError` (one line naming the file or key) for any bad
    input. ``require_uv=False`` accepts a mesh without texture coordinates (uniform fits).
    See the module docstring for every rule.
    """

    json_path = _json_path(Path(path))
    root = json_path.parent
    name = str(json_path)
    raw = _read_json(json_path)
    try:
        raw = without_nulls(raw)
    except RecursionError:  # parsed, but deeper than Python's stack walks
        raise CaptureError(f"{name}: invalid capture: JSON nested too deeply") from None

    # format and keys
    if "format" in raw:
        if raw["format"] != CAPTURE_FORMAT:
            raise CaptureError(f"{name}: format: expected {CAPTURE_FORMAT!r}, got {raw['format']!r}")
    elif not json_path.name.startswith("transforms"):
        raise CaptureError(f"{name}: missing key 'format' (expected {CAPTURE_FORMAT!r})")
    allowed_top = PBRFIT_TOP_LEVEL_KEYS + NERF_TOP_LEVEL_KEYS
    check_keys(raw, allowed_top, name, "the top level")
    check_distortion(raw, name)
    fisheye = raw.get("is_fisheye", False)
    if not (isinstance(fisheye, int) and fisheye in (0, 1)):  # true, false, 1 or 0; a string "false" is not false
        raise CaptureError(f"{name}: is_fisheye: expected true or false, got {fisheye!r:.40}")
    if fisheye:
        raise CaptureError(f"{name}: is_fisheye: fisheye cameras are not supported")
    if "camera_model" in raw and raw["camera_model"] not in PINHOLE_MODELS:
        raise CaptureError(
            f"{name}: camera_model: {raw['camera_model']!r} is not supported (expected one of {', '.join(PINHOLE_MODELS)})"
        )

    world_up = raw.get("world_up", "+y")
    if world_up not in WORLD_UPS:
        raise CaptureError(f"{name}: world_up: unknown value {world_up!r} (expected '+y' or '+z')")

    # images
    images = object_field(raw.get("images", {}), f"{name}: images")
    check_keys(images, _IMAGES_KEYS, f"{name}: images", "images")
    color_space_override = images.get("color_space")
    if color_space_override is not None and color_space_override not in COLOR_SPACES:
        raise CaptureError(
            f"{name}: images.color_space: unknown color space {color_space_override!r} (expected {' or '.join(COLOR_SPACES)})"
        )
    tonemap = images.get("tonemap", "none")
    if tonemap not in TONEMAPS:
        raise CaptureError(f"{name}: images.tonemap: unknown tone map {tonemap!r} (expected one of {', '.join(TONEMAPS)})")
    base_exposure = number_field(images, "exposure", f"{name}: images", 0.0)

    # lights, flash, environment
    lights_raw = raw.get("lights", [])
    if not isinstance(lights_raw, list):
        raise CaptureError(f"{name}: lights: expected a list of lights")
    global_lights = tuple(light_from_json(d, f"{name}: lights[{i}]") for i, d in enumerate(lights_raw))
    flash = _parse_flash(raw, name)
    environment = _parse_environment(raw, name, root)

    # mesh
    if "mesh" not in raw:
        raise CaptureError(f"{name}: missing key 'mesh' (the object's triangle mesh file)")
    mesh_path = root / string_field(raw, "mesh", name)
    mesh = load_mesh(mesh_path, f"{name}: mesh", require_uv=require_uv)

    # frames
    if "frames" not in raw:
        raise CaptureError(f"{name}: missing key 'frames'")
    frames_raw = raw["frames"]
    if not isinstance(frames_raw, list):
        raise CaptureError(f"{name}: frames: expected a list of frames")
    if not frames_raw:
        raise CaptureError(f"{name}: frames: no frames")
    frames = []
    for i, frame_raw in enumerate(frames_raw):
        frames.append(
            load_frame(raw, frame_raw, i, root, name, color_space_override, base_exposure, global_lights, flash)
        )

    # the space a fit compares in: the frames' own, or linear when their file types' defaults mix
    spaces = {f.color_space for f in frames}
    residual_space = frames[0].color_space if len(spaces) == 1 else "linear"
    truth = root / "truth"
    return Capture(
        root=root, mesh=mesh, mesh_path=mesh_path, world_up=world_up, frames=frames,
        environment=environment, color_space=residual_space, tonemap=tonemap,
        truth_dir=truth if truth.is_dir() else None, raw=raw, json_path=json_path,
        lights=global_lights, exposure=base_exposure,
    )  # fmt: skip
