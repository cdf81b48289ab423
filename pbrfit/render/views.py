"""A capture's views as shading inputs, rendering every view of a capture, and relighting it.

This is the glue between the capture (scene.py), the fixed geometry (gbuffer.py), the
environment (ibl.py) and shading (render.py): G-buffers are computed once per view (and cached
on disk when a cache folder is given), flattened into `ViewInputs`, and the environment's
split-sum tables are built once per capture. `pbrfit.render.output` writes the renders as a
capture folder.
"""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import CaptureError
from ..transfer import to_device
from ..scene.gbuffer import GBuffer, compute_gbuffer, silhouette
from ..io.json_fields import JSONError, parse_json
from ..physics.material import Material
from ..physics.model import Model
from .shade import ViewInputs, prepare_view, render_view
from ..lighting.environment import environment_lookup, load_environment
from ..lighting.ibl import IBLSettings, brdf_tables, build_ibl
from ..scene.capture import Capture, EnvironmentSpec, load_capture
from ..io.gltf_export import needs_texture_coordinates
from ..physics.color import encode
from ..scene.camera import pixel_offsets, sample_camera
from ..io.lights import light_from_json

__all__ = [
    "view_rows",
    "default_cache_dir",
    "model_for_capture",
    "capture_environment", "environment_is_dark",
    "capture_ibl",
    "capture_gbuffers",
    "capture_views",
    "render_capture",
    "apply_overrides",
    "load_lights_override",
]


def default_cache_dir() -> Path:
    """Where the CLI caches G-buffers: ``$PBRFIT_CACHE`` or ``$XDG_CACHE_HOME/pbrfit`` (~/.cache/pbrfit)."""
    if os.environ.get("PBRFIT_CACHE"):
        return Path(os.environ["PBRFIT_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pbrfit"


def model_for_capture(capture, material: Optional[Material] = None, **overrides) -> Model:
    """The model a capture requires: split-sum IBL only with an environment; the metal lobe only
    where `material` (when given) has metal somewhere. `overrides` set any other Model field."""
    fields = {"ibl": "split_sum" if capture.environment is not None else None}
    if material is not None:
        fields["metallic"] = bool(np.any(np.asarray(material.metallic) > 0.0))
    fields.update(overrides)
    return Model(**fields)


def check_environment(model: Model, capture) -> None:
    """`ValueError` when ``model`` shades an environment light (``model.ibl`` set) and the
    capture has no environment: there is nothing to build its tables from."""
    if model.ibl is not None and capture.environment is None:
        raise ValueError(f"model: Model(ibl={model.ibl!r}) shades an environment light, and the capture "
                         f"{capture.root} has none (leave ibl at None)")


def capture_environment(capture):
    """The capture's environment as a `pbrfit.lighting.environment.Environment`, or None."""
    if capture.environment is None:
        return None

    spec = capture.environment
    return load_environment(spec.file, capture.world_up, spec.intensity, spec.rotation_deg, spec.where)


def environment_is_dark(capture, environment=None) -> bool:
    """Whether no light comes from the capture's environment: there is none, or its radiance
    (times its intensity; negative values read as 0) is 0 everywhere. Reads the file unless
    ``environment`` holds it already (`capture_environment`'s)."""
    env = environment if environment is not None else capture_environment(capture)
    return env is None or not float(np.max(np.asarray(env.radiance), initial=0.0)) > 0.0


def capture_ibl(capture, settings=None, environment=None, model: Optional[Model] = None):
    """Split-sum tables for the capture's environment (or `environment`); `model` picks the lobes
    the tables hold (see `pbrfit.lighting.ibl.build_ibl`). Without an environment: the BRDF tables alone
    where ``model.multiscatter`` reads them (`pbrfit.lighting.ibl.brdf_tables`), else None."""

    env = environment if environment is not None else capture_environment(capture)
    if env is None:
        multiscatter = model is not None and model.multiscatter
        return brdf_tables(settings if settings is not None else IBLSettings(), model) if multiscatter else None

    return build_ibl(env, settings if settings is not None else IBLSettings(), model)


def capture_gbuffers(capture, cache_dir: Optional[os.PathLike] = None) -> list[GBuffer]:
    """One G-buffer per frame (shadow rays towards each of the frame's lights), the frames cast
    in a thread per core: the intersector and numpy's array operations release the GIL (the flash
    scene's 12 views of 128²: 0.16 s against 0.26 s one after another on 2 cores)."""
    frames = capture.frames

    def cast(frame):
        return compute_gbuffer(capture.mesh, frame.camera, frame.lights, cache_dir)

    workers = min(len(frames), os.cpu_count() or 1)
    if workers < 2:
        return [cast(f) for f in frames]
    with ThreadPoolExecutor(workers, thread_name_prefix="pbrfit-gbuffer") as pool:
        return list(pool.map(cast, frames))


def capture_views(capture, gbuffers: Sequence[GBuffer], use_masks: bool = True) -> list[ViewInputs]:
    """Shading inputs of every frame: the pixels where the mesh is hit (and, with `use_masks`,
    which the frame's mask keeps). A frame with neither a mask file nor alpha also loses the
    mesh's silhouette pixels (`pbrfit.scene.gbuffer.silhouette`): an antialiased image mixes the
    background into them, and nothing says by how much."""

    def mask(g, f):
        if not use_masks:
            return None
        if getattr(f, "mask_source", "none") == "none":
            return f.mask & ~silhouette(g.hit)
        return f.mask

    return [prepare_view(g, f.lights, mask(g, f)) for g, f in zip(gbuffers, capture.frames)]


def render_capture(
    capture,
    material: Material,
    model: Optional[Model] = None,
    ibl=None,
    gbuffers: Optional[Sequence[GBuffer]] = None,
    cache_dir: Optional[os.PathLike] = None,
    supersample: int = 1,
    environment=None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Render every frame as its file would hold it: [(image (H, W, 3), alpha (H, W))].

    Exposure, tone map and color space follow each frame; past the mesh, the camera sees the
    environment (or black without one). `supersample` k > 1 renders k × k samples per pixel,
    at the centres of a k × k grid of sub-pixels (`pbrfit.scene.camera.pixel_offsets`, the
    footprint `fit --pixel-samples k` models for k up to 4), and gives each pixel their mean
    linear radiance before the exposure, tone map and encoding (a supersampled renderer's or a
    camera's box footprint; time grows as k², memory does not); alpha is then 1 where every
    sample hits the mesh, 0 elsewhere (a pixel the silhouette crosses mixes the background in,
    as data_synth's masks leave it out), and `gbuffers` are not taken. `capture`: a
    `pbrfit.scene.capture.Capture` or its folder.
    Without `model`, the capture's (`model_for_capture`); without `ibl`, built from the
    capture's environment when the model needs it; `environment`: the capture's environment as
    `capture_environment` read it, else it is read here. A material holding NaN or inf, or a model
    that shades an environment the capture lacks, is refused (`ValueError`); material values
    outside [0, 1] are clipped (`pbrfit.render.shade.shading_inputs`).
    """

    if isinstance(capture, (str, os.PathLike)):
        capture = load_capture(capture, require_uv=needs_texture_coordinates(material))
    if not isinstance(capture, Capture):
        raise ValueError(f"capture: expected a pbrfit.scene.capture.Capture or a capture folder, got {type(capture).__name__}")
    for name in ("base_color", "metallic", "roughness", "normal", "occlusion", "emissive"):
        values = getattr(material, name)
        if values is not None and not np.all(np.isfinite(np.asarray(values))):
            raise ValueError(f"material: the {name} map holds NaN or inf values")
    model = model if model is not None else model_for_capture(capture, material)
    if ibl is None:
        check_environment(model, capture)
    environment = environment if environment is not None else capture_environment(capture)
    if ibl is None and (model.ibl == "split_sum" or model.multiscatter):
        ibl = capture_ibl(capture, environment=environment, model=model)
    k = int(supersample)
    if k != supersample or k < 1:
        raise ValueError(f"supersample must be an integer >= 1, got {supersample!r}")
    if k > 1:
        if gbuffers is not None:
            raise ValueError("gbuffers hold pixel centres only: pass gbuffers=None with supersample > 1")
        return [_render_supersampled(frame, capture, material, model, ibl, environment, k, cache_dir)
                for frame in capture.frames]
    gbuffers = gbuffers if gbuffers is not None else capture_gbuffers(capture, cache_dir)
    views = capture_views(capture, gbuffers, use_masks=False)
    out = []
    for frame, view in zip(capture.frames, views):
        background = None
        if environment is not None:  # what the camera sees past the mesh

            background = encode(_sky(environment, frame.camera), frame.exposure, capture.tonemap, frame.color_space)
        image, alpha = render_view(
            view, material, model, ibl, frame.exposure, capture.tonemap, frame.color_space, background=background
        )
        out.append((np.asarray(image), np.asarray(alpha)))
    return out


def _sky(environment, camera):
    """The environment's radiance along each pixel's ray (H · W, 3): what a camera sees past the mesh."""

    _, dirs = camera.rays()
    return environment_lookup(environment, jnp.asarray(dirs, jnp.float32))


def _render_supersampled(frame, capture, material, model, ibl, environment, k: int, cache_dir):
    """One frame of `render_capture` with k × k samples per pixel: rendered in linear radiance
    once per sample position (`pbrfit.scene.camera.pixel_offsets`, the frame's camera with its
    principal point moved so that its pixel centres fall there, as the fit's footprint samples
    them), averaged, then encoded as the frame's file holds it. Memory stays that of one sample."""

    c = frame.camera
    pixels = c.height * c.width
    total = np.zeros((pixels, 3), np.float64)
    every = np.ones(pixels, bool)
    for offset in pixel_offsets(k):
        camera = sample_camera(c, offset)
        view = prepare_view(compute_gbuffer(capture.mesh, camera, frame.lights, cache_dir), frame.lights, None)
        hits = np.asarray(view.pixel)
        sky = None if environment is None else _sky(environment, camera)
        if len(hits):
            radiance, _ = render_view(view, material, model, ibl, background=sky)  # linear, exposure 0
        else:
            radiance = np.zeros((pixels, 3)) if sky is None else sky
        total += np.asarray(radiance, np.float64).reshape(-1, 3)
        hit = np.zeros(pixels, bool)
        hit[hits] = True
        every &= hit
    radiance = jnp.asarray((total / (k * k)).reshape(c.height, c.width, 3), jnp.float32)
    image = encode(radiance, frame.exposure, capture.tonemap, frame.color_space)
    return np.asarray(image), every.reshape(c.height, c.width).astype(np.float32)


def load_lights_override(path: os.PathLike | str) -> list:
    """Read `--lights`: a JSON list of lights (or an object with a ``lights`` list), in a file or
    given inline (a string starting with ``[`` or ``{``)."""

    text = str(path).strip()
    if text.startswith(("[", "{")):
        path = "--lights"
        try:
            data = parse_json(text)
        except JSONError as err:
            raise CaptureError(f"--lights: {err}") from None
    elif not text:
        raise CaptureError("--lights: empty (a JSON list of lights, or a file holding one)")
    else:
        path = Path(path)
        try:
            data = parse_json(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise CaptureError(f"{path}: no such lights file") from None
        except JSONError as err:
            raise CaptureError(f"{path}: cannot read lights: {err}") from None
        except (OSError, UnicodeDecodeError) as err:
            raise CaptureError(f"{path}: cannot read lights: {err}") from None
    if isinstance(data, dict):
        data = data.get("lights")
    if not isinstance(data, list):
        raise CaptureError(f"{path}: expected a JSON list of lights")
    for i, light in enumerate(data):
        light_from_json(light, f"{path}: lights[{i}]")
    return data


def apply_overrides(capture, environment_file: Optional[os.PathLike] = None, lights_json: Optional[list] = None):
    """A copy of `capture` lit differently: another environment file and/or other global lights.

    Per-frame lights and the flash stay; the environment keeps its intensity and rotation.
    """

    changes = {}
    if environment_file is not None:
        path = Path(environment_file)
        if not path.is_file():
            raise CaptureError(f"{path}: no such environment file")
        old = capture.environment
        changes["environment"] = EnvironmentSpec(
            path, old.intensity if old else 1.0, old.rotation_deg if old else 0.0, "--environment"
        )
    if lights_json is not None:
        new_global = tuple(light_from_json(d, f"--lights[{i}]") for i, d in enumerate(lights_json))
        n_old = len(capture.lights)
        frames = [dataclasses.replace(f, lights=new_global + tuple(f.lights[n_old:])) for f in capture.frames]
        changes["frames"] = frames
        changes["lights"] = new_global
    return dataclasses.replace(capture, **changes) if changes else capture


def view_rows(view, pixels: np.ndarray):
    """`view` kept to `pixels` (sorted flat indices it holds)."""
    rows = np.searchsorted(np.asarray(view.pixel), pixels)
    return jax.tree_util.tree_map(lambda a: to_device(np.asarray(a)[rows]), view)  # every per-pixel array
