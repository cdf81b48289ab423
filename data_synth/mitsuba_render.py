"""A second, independent renderer for synthetic captures: Mitsuba 3's path tracer (the ``mitsuba`` extra).

`render_views` renders every view of a `presets.Scene` with Mitsuba's ``path`` integrator and
returns linear radiance per pixel with its standard error. The writer (`writer.render_scene`) does
the rest as for its own renderer: masks, exposure, tone map, sensor noise, files.

What is modelled: the glTF metallic-roughness BRDF as pbrfit's default `pbrfit.physics.model.Model`
computes it (`mitsuba_plugins` ``GltfBSDF``, a Python ``mi.BSDF``), textured from the truth maps;
the environment (``envmap``), point lights (``point``), spot lights and point lights with a ``range``
(``PunctualEmitter``, a Python ``mi.Emitter`` with KHR_lights_punctual's falloff) and directional
lights (``directional``);
every shadow and occlusion, environment light included, which pbrfit's Monte Carlo reference
leaves out; and with ``Scene.max_depth`` >= 3 light reflected between surfaces (2: direct light only).
Pixels are box-filtered over their area (Mitsuba's ``box`` filter), as the writer's supersampling
approximates.

Conventions, each derived here from pbrfit's own code and pinned by ``tests/test_synth_mitsuba.py``:

- camera: Mitsuba's camera looks down its +z with +x to the left of the image; a capture's
  camera-to-world (OpenGL: -z forward, +x right) becomes ``c2w @ diag(-1, 1, -1, 1)``, with the
  horizontal field of view (``fov_axis="x"``) and the film's row 0 at the top.
- textures: Mitsuba's ``bitmap`` texture reads uv as glTF does (row 0 at v = 0, texel centres at
  (k + 0.5) / N, bilinear, repeat), and the mesh is handed over with its glTF-oriented uv as they
  are (no loader flips them).
- environment (`environment_bitmap`): Mitsuba's envmap reads u = atan2(x, -z) / 2 pi in its own
  frame, half a turn from the spec's u = 0.5 + atan2(x, -z) / 2 pi, and puts image row k at the
  polar angle pi k / (H - 1) (rows at the poles), where pbrfit puts row i at pi (i + 0.5) / H and
  runs on to each pole's mean (`pbrfit.lighting.environment.sample_equirect`). The image handed over
  has 2H + 1 rows (each pbrfit row, the means of neighbours between them, the poles' means at the
  ends) and its columns turned by W // 2, and its ``to_world`` turns the rest of the half turn and
  maps the environment's frame (``world_up``, ``rotation_deg``) to the world: Mitsuba's bilinear
  lookup then equals pbrfit's in every direction.

Noise: each view is rendered in `PASSES` independent passes; the per-pixel standard error is the
spread of the pass means over sqrt(PASSES). The capture's noise level (`noise_level`) is the RMS of
that standard error over the pixels the mesh covers, relative to their mean radiance (worst view).
Without a set sample count, `render_views` starts at `FIRST_SPP` samples per pixel and raises it
until the noise is below `NOISE_TARGET` (at most `MAX_SPP`).

``import mitsuba`` happens in `load_mitsuba`, on first use: data_synth works without the extra.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Callable, Optional

import numpy as np

from .mitsuba_plugins import plugin_classes

__all__ = [
    "VARIANT",
    "MIN_LLVM",
    "NOISE_TARGET",
    "FIRST_SPP",
    "MAX_SPP",
    "PASSES",
    "SAMPLER",
    "MitsubaViews",
    "load_mitsuba",
    "check_scene",
    "mitsuba_to_world",
    "environment_bitmap",
    "environment_to_world",
    "render_views",
    "noise_level",
]

#: Mitsuba's variant: vectorised on the CPU through LLVM, so a Python BSDF runs once per wavefront
#: of rays (in a scalar variant it would run once per ray); RGB, as pbrfit renders.
VARIANT = "llvm_ad_rgb"
#: The oldest LLVM that compiles Dr.Jit 1.5's kernels: LLVM 15 and 16 abort the process ("Cannot
#: select: fminimum") on x86; Debian 12's libllvm19 works.
MIN_LLVM = 17
#: The largest noise level (`noise_level`) a render without a set sample count stops at: 0.5%.
NOISE_TARGET = 0.005
#: Samples per pixel of the first try when the sample count is not set.
FIRST_SPP = 64
#: The most samples per pixel a render without a set count goes to.
MAX_SPP = 16384
#: Independent passes per view, whose spread gives each pixel's standard error (15 degrees of freedom).
PASSES = 16
#: Mitsuba's sampler: jittered and Latin-hypercube stratified within each pass (a square number of
#: samples per pass). On a textured sphere under a sky and a lamp its noise at 256 samples per
#: pixel was 1.4% where the ``independent`` sampler's was 3.5%, and 0.27% at 4096, where 1 / sqrt(spp)
#: would leave the independent sampler at 0.9%.
SAMPLER = "multijitter"
#: Extra samples beyond the estimate when the noise was above the target (noise ~ 1 / sqrt(spp)).
SPP_MARGIN = 1.2
#: The most a render without a set sample count multiplies its count by from one try to the next:
#: the first try's estimate is rough, and the stratified sampler converges faster than 1 / sqrt(spp).
SPP_GROWTH = 16
#: Nearest distance a Mitsuba camera sees (world units): far below any capture's scale.
NEAR_CLIP = 1e-4

#: Model fields and the values `GltfBSDF` implements (the glTF BRDF of pbrfit's default Model).
_SUPPORTED = {"distribution": "ggx", "geometry": "smith_ggx_correlated", "fresnel": "schlick",
              "diffuse": "lambert", "multiscatter": False}


@dataclasses.dataclass(frozen=True)
class MitsubaViews:
    """What `render_views` rendered.

    Attributes:
        radiance: per view, (H, W, 3) float32 linear radiance (the mean over all samples).
        stderr: per view, (H, W, 3) float32 standard error of each value (one sigma).
        spp: samples per pixel.
        noise: the noise level (`noise_level`) over all views: the worst view's.
        variant: the Mitsuba variant, and ``version`` its version.
    """

    radiance: list
    stderr: list
    spp: int
    noise: float
    variant: str
    version: str

    def record(self, scene) -> dict:
        """What ``truth/synth.json`` says of the renderer."""
        return {
            "name": "mitsuba", "version": self.version, "variant": self.variant, "integrator": "path",
            "max_depth": int(scene.max_depth), "spp": int(self.spp), "pixel_filter": "box",
            "noise": round(float(self.noise), 6), "noise_target": NOISE_TARGET,
            "noise_measure": f"RMS over the mesh's pixels of each value's standard error (the spread of {PASSES} "
                             "independent passes), relative to their mean radiance; the worst view",
        }


# --- loading -----------------------------------------------------------------------------------
def load_mitsuba():
    """``(mitsuba, drjit)`` with `VARIANT` set; `pbrfit.errors.CaptureError` (one line) when the
    extra is not installed or its LLVM is missing or too old."""
    from pbrfit.errors import CaptureError

    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        raise CaptureError("--renderer mitsuba needs the mitsuba extra: pip install 'pbrfit[mitsuba]'") from None
    where = os.environ.get("DRJIT_LIBLLVM_PATH") or "the system's libLLVM"
    if not dr.has_backend(dr.JitBackend.LLVM):
        raise CaptureError(f"--renderer mitsuba: Dr.Jit found no LLVM library ({where}); install one "
                           f"(Debian 12: apt-get install libllvm19) and set DRJIT_LIBLLVM_PATH to it")
    version = tuple(dr.detail.llvm_version())
    if version[0] < MIN_LLVM:
        raise CaptureError(f"--renderer mitsuba: Dr.Jit loaded LLVM {'.'.join(map(str, version))} ({where}); it needs "
                           f"LLVM {MIN_LLVM} or newer: set DRJIT_LIBLLVM_PATH to a newer libLLVM "
                           "(Debian 12: apt-get install libllvm19; /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1)")
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi, dr


def check_scene(scene) -> None:
    """`pbrfit.errors.CaptureError` (one line) when `scene`'s model is not the BRDF `GltfBSDF` implements."""
    from pbrfit.errors import CaptureError

    model = scene.model
    for field, value in _SUPPORTED.items():
        if getattr(model, field) != value:
            raise CaptureError(f"synth {scene.name}: --renderer mitsuba implements the glTF BRDF "
                               f"({', '.join(f'{k}={v!r}' for k, v in _SUPPORTED.items())}); "
                               f"the scene's model has {field}={getattr(model, field)!r}")


# --- conventions -------------------------------------------------------------------------------
#: OpenGL camera axes (+x right, -z forward) -> Mitsuba's (+x left, +z forward).
_FLIP_XZ = np.diag([-1.0, 1.0, -1.0, 1.0])


def mitsuba_to_world(c2w: np.ndarray) -> np.ndarray:
    """The Mitsuba sensor ``to_world`` of an OpenGL camera-to-world matrix (unit axes)."""
    from pbrfit.scene.camera import camera_axes

    return camera_axes(np.asarray(c2w, np.float64)) @ _FLIP_XZ


def environment_bitmap(radiance: np.ndarray) -> np.ndarray:
    """(2H + 1, W, 3) float32: the image whose Mitsuba envmap lookup equals pbrfit's of the (H, W, 3)
    `radiance` (module docstring): row 2i + 1 is row i, row 2i the mean of rows i - 1 and i, rows 0
    and 2H the poles' means; columns turned left by W // 2."""
    img = np.asarray(radiance, np.float64)
    h, w = img.shape[:2]
    out = np.empty((2 * h + 1, w, img.shape[2]))
    out[1::2] = img
    out[2:-1:2] = 0.5 * (img[:-1] + img[1:])
    out[0] = img[0].mean(axis=0)
    out[-1] = img[-1].mean(axis=0)
    return np.ascontiguousarray(np.roll(out, -(w // 2), axis=1), dtype=np.float32)


def environment_to_world(width: int, world_up: str = "+y", rotation_deg: float = 0.0) -> np.ndarray:
    """4x4 ``to_world`` of Mitsuba's envmap holding `environment_bitmap` of a `width`-column map.

    pbrfit reads u_p = 0.5 + atan2(e_x, -e_z) / 2 pi of the environment-frame direction e = E d
    (`pbrfit.lighting.environment.to_environment_frame`, E orthonormal); Mitsuba reads
    u_m = atan2(l_x, -l_z) / 2 pi of l = T^-1 d. The bitmap's columns are turned by s = W // 2, so
    u_m must be u_p - s / W: l is e turned in azimuth by psi = pi - 2 pi s / W
    (l = M_psi e), and T = (M_psi E)^T."""
    import jax.numpy as jnp

    from pbrfit.lighting.environment import to_environment_frame

    e = np.asarray(to_environment_frame(jnp.eye(3, dtype=jnp.float32), world_up, rotation_deg), np.float64).T
    psi = math.pi - 2.0 * math.pi * (width // 2) / width
    c, s = math.cos(psi), math.sin(psi)
    m = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    out = np.eye(4)
    out[:3, :3] = (m @ e).T
    return out


# --- building the scene --------------------------------------------------------------------------
def _bitmap_texture(mi, values: np.ndarray):
    """Mitsuba's bilinear, repeating ``bitmap`` texture of linear (H, W, C) values."""
    bitmap = mi.Bitmap(np.ascontiguousarray(values, dtype=np.float32))
    return mi.load_dict({"type": "bitmap", "bitmap": bitmap, "raw": True, "filter_type": "bilinear",
                         "wrap_mode": "repeat"})


def gltf_bsdf(mi, dr, truth, model):
    """The `GltfBSDF` of a scene's truth maps (`textures.TruthMaps`) under `model`."""
    bsdf_class, _ = plugin_classes(mi, dr)
    return bsdf_class(mi.Properties(), _bitmap_texture(mi, truth.base_color), _bitmap_texture(mi, truth.metallic),
                      _bitmap_texture(mi, truth.roughness), model)


def _mesh(mi, mesh, bsdf):
    """A Mitsuba mesh of a `trimesh.Trimesh` (glTF-oriented uv, vertex normals) with `bsdf`."""
    vertices = np.asarray(mesh.vertices, np.float32)
    faces = np.asarray(mesh.faces, np.uint32)
    uv = np.asarray(mesh.visual.uv, np.float32)[:, :2]
    props = mi.Properties()
    props["bsdf"] = bsdf
    out = mi.Mesh("mesh", len(vertices), len(faces), props, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(out)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params["vertex_normals"] = mi.Float(np.asarray(mesh.vertex_normals, np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(uv.ravel())
    params.update()
    return out


def _light(mi, dr, light):
    """A Mitsuba emitter (dict or object) of a `pbrfit.physics.lights.Light`."""
    rgb = [float(c) * float(light.intensity) for c in np.asarray(light.color, np.float64)]
    if light.kind == "directional":
        return {"type": "directional", "direction": [float(x) for x in np.asarray(light.direction, np.float64)],
                "irradiance": {"type": "rgb", "value": rgb}}
    if light.kind == "point" and float(light.range) == 0.0:
        return {"type": "point", "position": [float(x) for x in np.asarray(light.position, np.float64)],
                "intensity": {"type": "rgb", "value": rgb}}
    _, emitter = plugin_classes(mi, dr)
    return emitter(mi.Properties(), light)


def _environment(mi, environment):
    """Mitsuba's envmap of a `pbrfit.lighting.environment.Environment` (its radiance already scaled)."""
    radiance = np.asarray(environment.radiance, np.float32)
    to_world = environment_to_world(radiance.shape[1], environment.world_up, environment.rotation_deg)
    return {"type": "envmap", "bitmap": mi.Bitmap(environment_bitmap(radiance)),
            "to_world": mi.ScalarTransform4f(to_world.tolist())}


def _sensor(mi, scene, c2w) -> dict:
    """The perspective camera of a frame, box-filtered pixels, `SAMPLER`."""
    return {
        "type": "perspective",
        "fov": math.degrees(float(scene.camera_angle_x)),
        "fov_axis": "x",
        "near_clip": NEAR_CLIP,
        "to_world": mi.ScalarTransform4f(mitsuba_to_world(c2w).tolist()),
        "sampler": {"type": SAMPLER},
        "film": {"type": "hdrfilm", "width": int(scene.width), "height": int(scene.height),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb", "component_format": "float32"},
    }


def view_scenes(scene, mesh, environment=None) -> list:
    """One Mitsuba scene per view of `scene`: the mesh with `GltfBSDF`, the view's lights (global,
    then the flash, as `writer` orders them), the environment, the camera, the path integrator."""
    from .writer import frame_lights

    mi, dr = load_mitsuba()
    check_scene(scene)
    shape = _mesh(mi, mesh, gltf_bsdf(mi, dr, scene.truth, scene.model))
    env = None if environment is None else _environment(mi, environment)
    out = []
    for c2w in scene.cameras:
        desc = {"type": "scene", "integrator": {"type": "path", "max_depth": int(scene.max_depth)},
                "mesh": shape, "sensor": _sensor(mi, scene, c2w)}
        if env is not None:
            desc["environment"] = env
        for k, light in enumerate(frame_lights(scene, c2w)):
            desc[f"light_{k}"] = _light(mi, dr, light)
        out.append(mi.load_dict(desc))
    return out


# --- rendering -----------------------------------------------------------------------------------
def noise_level(radiance: np.ndarray, stderr: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    """sqrt(mean SE^2) / mean L over the pixels of `mask` (all pixels where it is None or empty) and
    channels: the RMS standard error relative to the mean radiance."""
    keep = np.ones(radiance.shape[:2], bool) if mask is None or not np.any(mask) else np.asarray(mask, bool)
    mean = float(np.mean(radiance[keep], dtype=np.float64))
    rms = float(np.sqrt(np.mean(np.square(stderr[keep], dtype=np.float64))))
    return rms / mean if mean > 0 else (0.0 if rms == 0 else math.inf)


def _render_view(mi, mscene, spp: int, seed: int):
    """(mean, stderr) of one view: `PASSES` independent passes of spp / PASSES samples each, seeded
    seed, seed + 1, ..."""
    per_pass = spp // PASSES
    total = total2 = None
    for k in range(PASSES):
        image = np.asarray(mi.render(mscene, spp=per_pass, seed=(seed + k) & 0xFFFFFFFF), np.float64)
        total = image if total is None else total + image
        total2 = image * image if total2 is None else total2 + image * image
    mean = total / PASSES
    var = np.maximum(total2 - PASSES * mean * mean, 0.0) / (PASSES - 1)
    return mean.astype(np.float32), np.sqrt(var / PASSES).astype(np.float32)


def render_views(scene, mesh, environment=None, masks=None, spp: Optional[int] = None,
                 progress: Optional[Callable[[str], None]] = None) -> MitsubaViews:
    """Render every view of `scene` (see the module docstring) at its final size.

    `mesh`: a `trimesh.Trimesh` with glTF-oriented uv (as `pbrfit.scene.mesh.load_mesh` returns);
    `environment`: a `pbrfit.lighting.environment.Environment` or None; `masks`: per view, the
    (H, W) pixels the noise level is measured over (None: all); `spp`: samples per pixel, rounded
    up to `PASSES` passes of a square number (None: from `FIRST_SPP` up until the noise level is below
    `NOISE_TARGET`, at most `MAX_SPP`); the count used is in the result."""
    mi, _ = load_mitsuba()
    scenes = view_scenes(scene, mesh, environment)
    masks = [None] * len(scenes) if masks is None else list(masks)
    fixed = spp is not None
    count = _round_spp(FIRST_SPP if spp is None else int(spp))
    renders = 0  # each render's passes get seeds of their own, following the scene's seed
    while True:
        radiance, stderr = [], []
        for i, mscene in enumerate(scenes):
            mean, se = _render_view(mi, mscene, count, (int(scene.seed) << 20) + renders * PASSES)
            renders += 1
            radiance.append(mean)
            stderr.append(se)
            if progress:
                progress(f"mitsuba {count} spp: view {i + 1}/{len(scenes)}")
        noise = max(noise_level(r, s, m) for r, s, m in zip(radiance, stderr, masks))
        if fixed or noise <= NOISE_TARGET or count >= MAX_SPP:
            break
        wanted = count * min(SPP_GROWTH, SPP_MARGIN * (noise / NOISE_TARGET) ** 2)
        count = min(MAX_SPP, _round_spp(math.ceil(wanted)))
    if noise > NOISE_TARGET:
        import warnings

        warnings.warn(f"synth {scene.name}: Mitsuba's noise is {noise:.2%} at {count} samples per pixel, above "
                      f"{NOISE_TARGET:.1%} ({'--spp' if fixed else 'the most samples taken'}); truth/synth.json "
                      "records it", stacklevel=2)
    return MitsubaViews(radiance, stderr, count, float(noise), VARIANT, mi.__version__)


def _round_spp(spp: int) -> int:
    """spp rounded up to `PASSES` passes of a square number of samples each (`SAMPLER`)."""
    side = math.ceil(math.sqrt(max(int(spp), 1) / PASSES))
    return PASSES * side * side
