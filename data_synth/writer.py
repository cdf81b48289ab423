"""Render a `presets.Scene` and write it as a capture folder (``pbrfit-capture/1``) with ground truth.

The folder (built under a temporary name and renamed into place, so a failure leaves nothing):

    capture.json        cameras (camera_angle_x + transform_matrix), lights, flash, environment, images
    mesh.glb            the mesh with TEXCOORD_0 (glTF orientation) and normals
    env.exr             the environment (linear float32 equirect), when the scene has one
    images/NNN.exr|png  one image per camera (EXR linear float32, or 8/16-bit sRGB PNG)
    masks/NNN.png       8-bit, 255 where every supersample of the pixel hits the mesh (a Mitsuba
                        render's: where the pixel lies wholly on it, `mitsuba_masks`)
    truth/              the maps that rendered the images, in the fit-output layout
                        (base_color.exr/.png, metallic.exr, roughness.exr, metallic_roughness.png),
                        material.glb, and synth.json (preset, seed, parameters, model, renderer, sensor)
    contact_sheet.png   every view side by side (sRGB 8-bit)

Rendering uses the project's own path, so a fit sees exactly the geometry that made the images:
the mesh is read back from ``mesh.glb`` with `pbrfit.scene.mesh.load_mesh`, the environment from
``env.exr`` with `pbrfit.lighting.environment.load_environment`, the split-sum tables come from
`pbrfit.lighting.ibl.build_ibl` with default `IBLSettings`, G-buffers from `pbrfit.scene.gbuffer.compute_gbuffer`
(with each frame's lights in capture order: global lights, then the flash), and shading from
`pbrfit.render.shade.radiance_view` (with ``scene.model.ibl == "monte_carlo"``, the environment's share
comes from `pbrfit.lighting.montecarlo.monte_carlo_radiance` instead: ground truth, as a path tracer would
render direct light, the mesh's shadows of the environment on itself included, on the direction
cells a fit's occlusion is cast on, `_reference_visibility`). Each view is rendered at ``supersample`` times the size; where the
mesh is not hit the environment (or black) shows. The radiance is box-filtered down, exposed,
tone mapped and encoded (`pbrfit.physics.color.encode`); noise is added to those display values and
only then are they quantised to the file's bit depth.

With ``scene.renderer == "mitsuba"`` the radiance of each view comes from Mitsuba 3's path tracer
instead (`data_synth.mitsuba_render`, the ``mitsuba`` extra), at the final size with each pixel the
mean over its area; the masks come from pbrfit's G-buffers at `MITSUBA_MASK_SAMPLES` (or
``supersample``, the larger) samples per side and the samples around each pixel's corners, so that
they hold the pixels wholly on the mesh (`mitsuba_masks`); the encoding, the noise and the files are
the same.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from . import noise as sensor
from .environments import write_environment
from .meshes import write_glb
from .presets import IMAGE_FORMATS, Scene

__all__ = ["SynthResult", "synthesize", "render_scene", "frame_camera", "mitsuba_masks", "contact_sheet", "capture_json"]

#: Pixels per compiled shading call: every view's pixels are shaded together in chunks of this
#: size (the tail padded), so one compilation serves the whole capture.
SHADE_CHUNK = 16384
#: Samples per side of a pixel that the masks of a Mitsuba render test (`mitsuba_masks`): Mitsuba's
#: pixel is the mean over its whole area, so a pixel whose centre alone is on the mesh mixes in
#: what lies beyond the silhouette (the sky). The samples of the neighbouring pixels next to it are
#: tested too (`_whole_pixels`): 4 x 4 samples alone let a silhouette cut off a strip up to 1/8 of a
#: pixel wide between them (on torus-floor, pixels at the floor's far edge with 2-8% of their area
#: off it, where the sky mixed into the sun's glint and pulled the fit's roughness there).
MITSUBA_MASK_SAMPLES = 4


@dataclasses.dataclass
class SynthResult:
    """What `synthesize` wrote and rendered.

    Attributes:
        path: the capture folder.
        scene: the scene.
        images: per view, the display values as written (noise and quantisation included), float32.
        clean: per view, the display values before noise and quantisation.
        masks: per view, (H, W) bool.
        seconds: wall time.
        renderer: what rendered the radiance, as ``truth/synth.json`` records it (``name``, and for
            Mitsuba its version, variant, max_depth, samples per pixel and noise level).
    """

    path: Path
    scene: Scene
    images: list
    clean: list
    masks: list
    seconds: float
    renderer: dict = dataclasses.field(default_factory=dict)


def frame_camera(scene: Scene, c2w: np.ndarray, supersample: int = 1):
    """The `pbrfit.scene.camera.Camera` of a frame (as `pbrfit.scene.capture.load_capture` builds it from
    ``camera_angle_x``), at `supersample` times the image size."""
    from pbrfit.scene.camera import Camera

    k = int(supersample)
    return Camera.from_fov(c2w, scene.camera_angle_x, scene.width * k, scene.height * k)


def frame_lights(scene: Scene, c2w: np.ndarray) -> tuple:
    """The lights of a frame, in capture order: the global lights, then the flash."""
    from pbrfit.physics.lights import flash_light

    lights = tuple(scene.lights)
    if scene.flash is not None:
        f = scene.flash
        lights = lights + (flash_light(c2w, f.color, f.intensity, f.offset),)
    return lights


def render_scene(scene: Scene, mesh, environment=None, ibl=None, progress: Optional[Callable[[str], None]] = None):
    """Clean display values, masks and the renderer's record of every view:
    ([(H, W, 3) float32], [(H, W) bool], dict).

    `mesh`: a `trimesh.Trimesh` with glTF-oriented uv (as `pbrfit.scene.mesh.load_mesh` returns);
    `environment`: a `pbrfit.lighting.environment.Environment` or None; `ibl`: its split-sum tables when
    ``scene.model.ibl == "split_sum"`` (or ``model.multiscatter``); with ``"monte_carlo"`` the
    environment light is integrated per pixel sample by the reference (`Scene.mc_samples`). With
    ``scene.renderer == "mitsuba"`` the radiance comes from Mitsuba's path tracer instead
    (`data_synth.mitsuba_render.render_views`, which ignores `ibl`); masks and encoding are the same.
    """
    from pbrfit.physics.color import encode

    if scene.renderer == "mitsuba":
        from .mitsuba_render import render_views  # the optional extra: imported only when asked for

        masks = mitsuba_masks(scene, mesh, progress)
        views = render_views(scene, mesh, environment, masks, scene.spp, progress)
        radiance, record = views.radiance, views.record(scene)
    else:
        radiance, masks = _render_pbrfit(scene, mesh, environment, ibl, progress)
        record = {"name": "pbrfit"}
    images = [np.asarray(encode(img, float(ev), scene.tonemap, scene.color_space), np.float32)
              for img, ev in zip(radiance, scene.exposures)]
    return images, masks, record


def _mask(hit: np.ndarray, supersample: int) -> np.ndarray:
    """(H, W) bool: the pixels all of whose `supersample` x `supersample` samples hit the mesh."""
    return sensor.box_downsample(np.asarray(hit, np.float32)[..., None], int(supersample))[..., 0] >= 1.0


def _whole_pixels(hit: np.ndarray, supersample: int) -> np.ndarray:
    """(H, W) bool: the pixels wholly on the mesh, as a grid of k x k samples per pixel (spacing 1/k)
    tells: every sample of the pixel and every sample next to one of them hits.

    The window of (k + 2)^2 samples holds the four samples around each of the pixel's corners. A
    straight silhouette edge that enters the pixel leaves a corner c on its far side, and then one of
    the four samples c + (±1/2k, ±1/2k) too (their mean is c), however thin the sliver it cuts off;
    the k x k samples alone miss strips up to 1/(2k) of the pixel wide along a side. Samples past the
    image's border repeat the border's."""
    from scipy import ndimage

    padded = np.pad(np.asarray(hit, bool), 1, mode="edge")  # as pbrfit.scene.uv_layout's _interior
    return _mask(ndimage.binary_erosion(padded, np.ones((3, 3), bool))[1:-1, 1:-1], supersample)


def mitsuba_masks(scene: Scene, mesh, progress=None) -> list:
    """Per view, (H, W) bool: the masks of a Mitsuba render, the pixels wholly on the mesh
    (`_whole_pixels` of k x k samples, k the larger of ``scene.supersample`` and
    `MITSUBA_MASK_SAMPLES`; a Mitsuba pixel is the mean over its area, at any supersampling)."""
    k = max(int(scene.supersample), MITSUBA_MASK_SAMPLES)
    return [_whole_pixels(hit, k) for hit in _hits(scene, mesh, progress, k)]


def _hits(scene: Scene, mesh, progress=None, k: int = 1) -> list:
    """Per view, (H k, W k) bool: where the rays through the centres of k x k samples per pixel hit the mesh."""
    from pbrfit.scene.gbuffer import compute_gbuffer

    hits = []
    for i, c2w in enumerate(scene.cameras):
        hits.append(np.asarray(compute_gbuffer(mesh, frame_camera(scene, c2w, k)).hit, bool))
        if progress:
            progress(f"geometry {i + 1}/{scene.num_views}")
    return hits


def _pad_rows(tree, size: int):
    """Every (host) array of ``tree`` padded to ``size`` rows with copies of its last row, with
    numpy: a concatenation run eagerly by JAX compiles once per shape."""
    import jax

    return jax.tree_util.tree_map(lambda a: np.concatenate([a, np.repeat(a[-1:], size - len(a), axis=0)]), tree)


def _render_pbrfit(scene: Scene, mesh, environment=None, ibl=None, progress=None):
    """pbrfit's own radiance and masks of every view: ([(H, W, 3) float32], [(H, W) bool]); see `render_scene`."""
    import jax.numpy as jnp

    from pbrfit.lighting.environment import environment_lookup
    from pbrfit.scene.gbuffer import compute_gbuffer
    from pbrfit.render.shade import ViewInputs, prepare_view, radiance_view

    k = int(scene.supersample)
    hk, wk = scene.height * k, scene.width * k
    material = scene.truth.to_material()
    views, hits, backgrounds, surface = [], [], [], []
    for i, c2w in enumerate(scene.cameras):
        camera = frame_camera(scene, c2w, k)
        lights = frame_lights(scene, c2w)
        gbuffer = compute_gbuffer(mesh, camera, lights)
        views.append(prepare_view(gbuffer, lights))
        hit = np.asarray(gbuffer.hit, bool)
        hits.append(hit)
        if scene.model.ibl == "monte_carlo":  # the points and their faces' normals, as prepare_view orders them
            surface.append((np.asarray(gbuffer.position)[hit], np.asarray(gbuffer.geometric_normal)[hit]))
        if environment is not None:
            _, dirs = camera.rays()
            backgrounds.append(np.asarray(environment_lookup(environment, jnp.asarray(dirs, jnp.float32))))
        else:
            backgrounds.append(None)
        if progress:
            progress(f"geometry {i + 1}/{scene.num_views}")
    # every view's pixels in one flat batch: one compilation for the whole capture
    fields = ("pixel", "uv", "normal", "tangent", "view", "light_l", "light_radiance")
    batch = ViewInputs(  # on the host, as the padding (`_pad_rows`): no compile per capture size
        **{f: np.concatenate([np.asarray(getattr(v, f)) for v in views], axis=0) for f in fields},
        shape=(1, sum(v.num_pixels for v in views)),
    )
    total = batch.num_pixels
    if 0 < total < SHADE_CHUNK:  # pad to a power of two: small captures share compilations
        batch = _pad_rows(batch, 1 << (total - 1).bit_length())
    if scene.model.ibl == "monte_carlo":  # punctual light as usual, the environment by the reference integrator
        radiance = radiance_view(batch, material, scene.model.replace(ibl=None), ibl, chunk=SHADE_CHUNK)
        visibility = _reference_visibility(mesh, environment, surface, progress)
        radiance = np.asarray(radiance, np.float32) + _monte_carlo_environment(
            batch, material, scene.model, environment, int(scene.mc_samples), progress, visibility)
        radiance = radiance[:total]
    else:
        radiance = np.asarray(radiance_view(batch, material, scene.model, ibl, chunk=SHADE_CHUNK), np.float32)[:total]
    if progress:
        progress("shaded")
    out_images, out_masks = [], []
    start = 0
    for view, hit, bg in zip(views, hits, backgrounds):
        n = view.num_pixels
        img = np.zeros((hk * wk, 3), np.float32) if bg is None else bg.reshape(-1, 3).astype(np.float32)
        img[np.asarray(view.pixel)] = radiance[start : start + n]
        start += n
        out_images.append(sensor.box_downsample(img.reshape(hk, wk, 3), k))
        out_masks.append(_mask(hit, k))
    return out_images, out_masks


def _reference_visibility(mesh, environment, surface, progress=None):
    """The environment's visibility from every view's hit points, ``surface`` [(points (P, 3),
    geometric normals (P, 3))] in the batch's order, for the Monte Carlo reference: the mesh's
    shadows of the environment on itself, a shadow ray per point and direction cell
    (`pbrfit.scene.occlusion.cast_visibility`, the cells a fit's occlusion is cast on), or None
    where no face has the mesh above it (a convex mesh: nothing to cast)."""
    from pbrfit.scene.occlusion import cast_visibility, occluding_faces

    if not occluding_faces(mesh).any():
        return None
    points, normals = (np.concatenate([part[i] for part in surface]) for i in (0, 1))
    visibility, _ = cast_visibility(mesh, environment, points, normals)
    if progress:
        progress(f"environment visibility of {len(points)} points")
    return visibility


def _monte_carlo_environment(batch, material, model, environment, samples: int, progress=None,
                             visibility=None) -> np.ndarray:
    """(P, 3) environment light reflected at the batch's points by the Monte Carlo reference, in
    chunks of `SHADE_CHUNK` points (each chunk seeded by its first point's index, each point with
    its own stream within it: reproducible, and independent from point to point); ``visibility``:
    the first rows' `pbrfit.lighting.visibility.Visibility` (`_reference_visibility`; rows past
    it, the batch's padding, see everything), or None: no occlusion."""
    import jax

    from pbrfit.lighting.montecarlo import monte_carlo_radiance
    from pbrfit.lighting.visibility import visibility_rows
    from pbrfit.render.shade import shading_inputs

    out = []
    total = batch.num_pixels
    for start in range(0, total, SHADE_CHUNK):
        view = jax.tree_util.tree_map(lambda a: np.asarray(a)[start:start + SHADE_CHUNK], batch)
        n = view.normal.shape[0]
        if n < SHADE_CHUNK and total > SHADE_CHUNK:  # pad the tail: one compilation
            view = _pad_rows(view, SHADE_CHUNK)
        normal, base_color, metallic, roughness, occlusion, _ = shading_inputs(view, material)  # as radiance_view
        rows = None
        if visibility is not None:  # the chunk's rows that have points, then padding that sees everything
            lo, hi = (min(i, visibility.num_points) for i in (start, start + len(normal)))
            rows = visibility_rows(visibility, lo, hi, len(normal) - (hi - lo))
        rad = monte_carlo_radiance(environment, normal, view.view, base_color, metallic, roughness, model,
                                   samples=samples, key=jax.random.PRNGKey(start), visibility=rows)
        if occlusion is not None:  # occlusion scales environment light (`pbrfit.render.shade.shade`)
            rad = rad * occlusion
        out.append(np.asarray(rad, np.float32)[:n])
        if progress:
            progress(f"environment (Monte Carlo) {min(start + SHADE_CHUNK, total)}/{total}")
    return np.concatenate(out) if out else np.zeros((0, 3), np.float32)


def capture_json(scene: Scene, image_paths, mask_paths, has_env: bool) -> dict:
    """The capture.json object of a scene (capture spec ``pbrfit-capture/1``)."""
    from pbrfit.io.lights import light_to_json

    raw = {
        "format": "pbrfit-capture/1",
        "mesh": "mesh.glb",
        "world_up": scene.world_up,
        "camera_angle_x": float(scene.camera_angle_x),
        "frames": [
            {
                "file_path": img,
                "transform_matrix": [[float(x) for x in row] for row in c2w],
                "mask_path": mask,
                "exposure": float(ev),
            }
            for img, mask, c2w, ev in zip(image_paths, mask_paths, scene.cameras, scene.exposures)
        ],
        "lights": [light_to_json(light) for light in scene.lights],
        "images": {"color_space": scene.color_space, "tonemap": scene.tonemap},
    }
    if scene.flash is not None:
        raw["flash"] = {
            "color": [float(c) for c in scene.flash.color],
            "intensity": float(scene.flash.intensity),
            "offset": [float(c) for c in scene.flash.offset],
        }
    if has_env:
        raw["environment"] = {"file": "env.exr", "intensity": float(scene.environment_intensity), "rotation_deg": 0.0}
    return raw


def _dumps(obj) -> str:
    """JSON with two-space indents, but lists of numbers (matrix rows, colours) on one line."""
    text = json.dumps(obj, indent=2)
    return re.sub(r"\[\s+([-+0-9.eE,\s]+?)\s+\]", lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)


def contact_sheet(images, color_space: str, columns: Optional[int] = None, gap: int = 2) -> np.ndarray:
    """(H', W', 3) sRGB-encoded [0, 1] mosaic of the views, row-major, `gap` black pixels apart."""
    from pbrfit.physics.color import linear_to_srgb_host

    n = len(images)
    columns = columns or int(math.ceil(math.sqrt(n)))
    rows = int(math.ceil(n / columns))
    h, w = images[0].shape[:2]
    sheet = np.zeros((rows * (h + gap) - gap, columns * (w + gap) - gap, 3), np.float32)
    for i, img in enumerate(images):
        tile = np.clip(img, 0.0, 1.0)
        if color_space == "linear":
            tile = linear_to_srgb_host(tile)
        r, c = divmod(i, columns)
        sheet[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = tile
    return sheet


def _synth_json(scene: Scene, seconds: float, renderer: dict) -> dict:
    def plain(x):
        if isinstance(x, (np.floating, np.integer)):
            return x.item()
        if isinstance(x, (tuple, list, np.ndarray)):
            return [plain(v) for v in np.asarray(x, dtype=object).tolist()] if isinstance(x, np.ndarray) else [plain(v) for v in x]
        return x

    return {
        "preset": scene.name,
        "seed": scene.seed,
        "params": {k: plain(v) for k, v in scene.params.items()},
        "model": scene.model.describe(),
        "renderer": renderer,
        "ibl_settings": None if scene.renderer != "pbrfit" else {
            "split_sum": "pbrfit.lighting.ibl.IBLSettings() defaults",
            "monte_carlo": f"pbrfit.lighting.montecarlo.monte_carlo_radiance, {int(scene.mc_samples)} samples"
        }.get(scene.model.ibl),
        "image_format": scene.image_format,
        "color_space": scene.color_space,
        "tonemap": scene.tonemap,
        "supersample": int(scene.supersample),
        "noise": {"sigma": float(scene.noise), "model": scene.noise_model,
                  "applied_to": "display values, after supersampling, before quantisation"},
        "texture_size": list(scene.truth.shape),
        "views": scene.num_views,
        "image_size": [scene.width, scene.height],
        "seconds": round(seconds, 3),
    }


def synthesize(
    scene: Scene,
    out,
    *,
    overwrite: bool = True,
    write_contact_sheet: bool = True,
    progress: Optional[Callable[[str], None]] = None,
) -> SynthResult:
    """Render `scene` and write its capture folder at `out` (see the module docstring)."""
    from pbrfit.lighting.environment import load_environment
    from pbrfit.io.atomic import atomic_dir
    from pbrfit.io.gltf_export import write_gltf
    from pbrfit.io.images import write_image
    from pbrfit.io.material_files import write_material
    from pbrfit.scene.mesh import load_mesh

    t0 = time.perf_counter()
    suffix, dtype, color_space, bits = IMAGE_FORMATS[scene.image_format]
    out = Path(out)
    with atomic_dir(out, overwrite=overwrite, kind="capture") as tmp:
        tmp = Path(tmp)
        write_glb(tmp / "mesh.glb", scene.mesh)
        mesh = load_mesh(tmp / "mesh.glb")  # what a fit will see
        environment = ibl = None
        if scene.environment is not None:
            write_environment(tmp / "env.exr", scene.environment)
            environment = load_environment(tmp / "env.exr", scene.world_up, scene.environment_intensity, 0.0)
            if scene.renderer == "pbrfit" and (scene.model.ibl == "split_sum" or scene.model.multiscatter):
                from pbrfit.lighting.ibl import IBLSettings, build_ibl

                ibl = build_ibl(environment, IBLSettings(), scene.model)
        elif scene.renderer == "pbrfit" and scene.model.multiscatter:  # punctual lights alone: compensation tables
            from pbrfit.lighting.ibl import brdf_tables

            ibl = brdf_tables(model=scene.model)
        clean, masks, renderer = render_scene(scene, mesh, environment, ibl, progress)

        rng = np.random.default_rng([scene.seed, 0x5E5])  # the sensor's own stream
        images = [sensor.quantize(sensor.add_noise(c, scene.noise, rng, scene.noise_model), bits) for c in clean]
        image_paths = [f"images/{i:03d}{suffix}" for i in range(scene.num_views)]
        mask_paths = [f"masks/{i:03d}.png" for i in range(scene.num_views)]
        for img, mask, ip, mp in zip(images, masks, image_paths, mask_paths):
            write_image(tmp / ip, img, dtype, color_space=color_space)
            write_image(tmp / mp, mask.astype(np.float32)[..., None], "uint8", color_space="linear")
        raw = capture_json(scene, image_paths, mask_paths, environment is not None)
        (tmp / "capture.json").write_text(_dumps(raw) + "\n")

        truth = tmp / "truth"
        material = scene.truth.to_material()
        write_material(truth, material)
        write_gltf(truth / "material.glb", mesh, material, scene.world_up)  # mesh: glTF-oriented uv, as loaded
        if write_contact_sheet:
            write_image(tmp / "contact_sheet.png", contact_sheet(images, color_space), "uint8")
        seconds = time.perf_counter() - t0
        (truth / "synth.json").write_text(json.dumps(_synth_json(scene, seconds, renderer), indent=2) + "\n")
    return SynthResult(out, scene, images, clean, masks, time.perf_counter() - t0, renderer)
