"""A capture's frames: each ``frames[i]`` of ``capture.json`` read into a `Frame` (its image in
linear float32, mask, saturated and non-finite pixels, camera, lights and exposure; the rules:
`pbrfit.scene.capture`'s docstring), and image paths as NeRF writes them (`resolve_image_path`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from .capture_cameras import camera_to_world, check_distortion, frame_camera
from ..errors import CaptureError
from .camera import Camera
from ..io.images import _LDR_MAX, ImageInfo, color_channels, data_window_mask, read_image, srgb_decoded
from ..io.json_fields import check_keys, field_loc, number_field, object_field, string_field
from ..io.lights import light_from_json
from ..physics.lights import Light, flash_light

__all__ = ["Frame", "load_frame", "resolve_image_path", "PBRFIT_FRAME_KEYS", "NERF_FRAME_KEYS", "IMAGE_SUFFIXES",
           "MAX_EXPOSURE"]

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
