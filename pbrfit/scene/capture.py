"""Captures: loading and validating ``capture.json`` (spec: ``pbrfit-capture/1``).

`load_capture` turns a capture folder into a `Capture`: the mesh, one `Frame` per image (pixels
in linear float32, mask, camera, lights, exposure), the environment and the image encoding.
Every problem with the input raises `pbrfit.errors.CaptureError` with one line naming the file or
key and what is wrong. The frames are read by `pbrfit.scene.capture_frames`, their cameras by
`pbrfit.scene.capture_cameras`, and every field is checked by `pbrfit.io.json_fields`.

Rules pinned here (tests in ``tests/test_scene.py``):

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

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from .capture_cameras import PINHOLE_MODELS, check_distortion
from .capture_frames import IMAGE_SUFFIXES, NERF_FRAME_KEYS, PBRFIT_FRAME_KEYS, Frame, load_frame, resolve_image_path
from ..errors import CaptureError
from ..io.images import read_image_info
from ..io.json_fields import JSONError, check_keys, parse_json, number_field, object_field, string_field, triple_field, without_nulls
from ..io.lights import color_and_intensity, light_from_json
from ..physics.lights import Light
from .mesh import load_mesh

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
]

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
    from ..physics.color import COLOR_SPACES, TONEMAPS

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
