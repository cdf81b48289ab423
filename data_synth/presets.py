"""Scene presets: everything a synthetic capture needs, reproducible from a seed.

A `Scene` is plain data: mesh (`meshes.MeshData`), ground-truth maps (`textures.TruthMaps`),
cameras (camera-to-world, OpenGL), intrinsics, punctual lights and flash, an optional
environment image, the image encoding, the sensor model (supersampling, noise, quantisation)
and the reflectance `Model` that renders it. `make_scene(name, seed=..., **overrides)` builds a
preset; `writer.synthesize(scene, out)` renders and writes it.

Presets (`PRESETS`):

- ``peer-plane``: the fitting issue's peer scene: Z-up 2 x 2 plane, 6 views of 128^2 at 45 deg
  horizontal fov from 2.9 units, 4 white point lights of intensity 6 cd at 2.6 units, 64^2
  textured maps with metallic 0; linear EXR, noiseless (``noise=0.01`` for the noisy variant).
- ``plane-flash``: a floor shot with a phone: 12 handheld views, a flash on every camera plus
  two lamps, binary metallic (gold metal), 16-bit sRGB PNGs, 2 x 2 supersampled, 1% noise.
- ``sphere-env``: a textured sphere (binary gold metal) under a procedural sky, 8 views, EXR.
- ``spheres-grid``: the metallic x roughness chart: 5 x 5 spheres, metallic down the rows and
  roughness across the columns, in a studio with a key light, 6 views from the front, EXR.
- ``mesh-env``: any mesh (default a torus; ``shape="box"`` a rounded box, ``mesh=PATH`` a user's
  mesh with uv) under a studio environment, 10 hemisphere views, EXR.
- ``demo``: a sphere on a floor under a procedural sky plus a sun-like point light, textured
  truth in a two-tile atlas, 8 views of 96^2, small noise: synthesizes in a few seconds.
- ``sphere-floor``, ``torus-floor``: a sphere (or a torus, lying flat) resting on a textured
  floor under a sky with a sun and no other light, textured truth with binary metallic in a
  two-tile atlas (floor left, object right), 12 views of 96^2, EXR: the object's shadow on the
  floor and its own occlusion (the torus's hole, the sphere's underside) are the environment's,
  for the fit's environment occlusion (`pbrfit.lighting.visibility`); render them with
  ``ibl="monte_carlo"`` for images with the shadows in.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, Optional

import numpy as np

from . import environments, meshes, rigs, textures
from .meshes import MeshData
from .textures import TruthMaps

__all__ = ["Scene", "Flash", "PRESETS", "IMAGE_FORMATS", "RENDERERS", "MIN_DEPTH", "INTERREFLECTION_DEPTH",
           "make_scene", "preset_names", "describe_presets"]

#: Image file types a scene can be written as: (suffix, OpenImageIO pixel type, color space,
#: quantisation bits (0 = float)).
IMAGE_FORMATS = {
    "exr": (".exr", "float", "linear", 0),
    "png16": (".png", "uint16", "srgb", 16),
    "png8": (".png", "uint8", "srgb", 8),
}

#: What renders a scene: pbrfit's own renderer, or Mitsuba 3's path tracer (the ``mitsuba`` extra).
RENDERERS = ("pbrfit", "mitsuba")
#: The least ``Scene.max_depth``: the camera's vertex and one towards a light (direct light).
MIN_DEPTH = 2
#: ``Scene.max_depth`` of the presets whose mesh is not convex: direct light and light reflected up
#: to twice between surfaces.
INTERREFLECTION_DEPTH = 4


@dataclasses.dataclass(frozen=True)
class Flash:
    """A light on every camera (capture.json ``flash``): offset in camera space."""

    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 1.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A synthetic capture before rendering. See the module docstring.

    Attributes:
        name: the preset's name.
        seed: the seed every random choice came from.
        mesh: geometry with glTF-oriented uv (world units, `world_up` up).
        truth: the maps that render the images.
        cameras: (N, 4, 4) camera-to-world matrices (OpenGL).
        camera_angle_x: horizontal field of view, radians.
        width, height: image size in pixels (after supersampling).
        lights: global punctual lights (`pbrfit.physics.lights.Light`).
        flash: a light on every camera, or None.
        environment: (He, We, 3) linear equirect radiance in the capture spec's orientation, or None.
        environment_intensity: capture.json ``environment.intensity``.
        world_up: ``"+y"`` or ``"+z"``.
        exposures: (N,) per-frame EV.
        tonemap: operator applied after exposure.
        image_format: a key of `IMAGE_FORMATS`.
        supersample: k: rendered at k x the size, box-filtered down.
        noise: noise strength (std at a display value of 1); 0 = none.
        noise_model: ``"gaussian"``, ``"relative"`` or ``"poisson_gaussian"`` (`data_synth.noise`).
        model: the `pbrfit.physics.model.Model` that renders the images. With ``ibl="monte_carlo"`` the
            environment light is rendered by the reference integrator
            (`pbrfit.lighting.montecarlo.monte_carlo_radiance`, ``mc_samples`` steps per pixel sample)
            rather than the split sum: ground truth, as a path tracer would render it.
        mc_samples: see ``model``.
        renderer: ``"pbrfit"`` (the project's own renderer, as ``model`` says) or ``"mitsuba"`` (Mitsuba 3's
            path tracer, `data_synth.mitsuba_render`: every shadow, and light between surfaces).
        max_depth: ``"mitsuba"``: the path tracer's longest path, camera vertex included: 2 is direct
            light only, 3 and more add light reflected between surfaces. The presets pick 2 for a
            convex mesh (where nothing else is there to reflect) and `INTERREFLECTION_DEPTH` otherwise.
        spp: ``"mitsuba"``: samples per pixel; None: as many as bring the noise below
            `data_synth.mitsuba_render.NOISE_TARGET`.
        params: the preset's parameters, for ``truth/synth.json``.
    """

    name: str
    seed: int
    mesh: MeshData
    truth: TruthMaps
    cameras: np.ndarray
    camera_angle_x: float
    width: int
    height: int
    lights: tuple = ()
    flash: Optional[Flash] = None
    environment: Optional[np.ndarray] = None
    environment_intensity: float = 1.0
    world_up: str = "+y"
    exposures: Optional[np.ndarray] = None
    tonemap: str = "none"
    image_format: str = "exr"
    supersample: int = 1
    noise: float = 0.0
    noise_model: str = "gaussian"
    model: Any = None
    mc_samples: int = 1024
    renderer: str = "pbrfit"
    max_depth: int = MIN_DEPTH
    spp: Optional[int] = None
    params: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        from pbrfit.physics.model import Model

        if self.image_format not in IMAGE_FORMATS:
            raise ValueError(f"image_format must be one of {sorted(IMAGE_FORMATS)}, got {self.image_format!r}")
        cams = np.asarray(self.cameras, np.float64)
        if cams.ndim != 3 or cams.shape[1:] != (4, 4) or len(cams) == 0:
            raise ValueError(f"cameras must be (N, 4, 4) with N >= 1, got {cams.shape}")
        object.__setattr__(self, "cameras", cams)
        ex = np.zeros(len(cams)) if self.exposures is None else np.asarray(self.exposures, np.float64)
        object.__setattr__(self, "exposures", np.broadcast_to(ex, (len(cams),)).copy())
        if self.model is None:
            ibl = "split_sum" if self.environment is not None else None
            object.__setattr__(self, "model", Model(ibl=ibl))
        if int(self.mc_samples) < 1:
            raise ValueError(f"mc_samples must be >= 1, got {self.mc_samples}")
        if int(self.supersample) < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        if int(self.max_depth) < MIN_DEPTH:
            raise ValueError(f"max_depth must be >= {MIN_DEPTH} (direct light), got {self.max_depth}")
        if self.spp is not None and int(self.spp) < 1:
            raise ValueError(f"spp must be >= 1 or None, got {self.spp}")

    @property
    def color_space(self) -> str:
        return IMAGE_FORMATS[self.image_format][2]

    @property
    def num_views(self) -> int:
        return len(self.cameras)

    def replace(self, **changes) -> "Scene":
        return dataclasses.replace(self, **changes)


# --- the presets -------------------------------------------------------------------------------
def _common(kw: dict, defaults: dict) -> dict:
    """Defaults overridden by the caller's non-None keywords; unknown keywords are an error."""
    kw = {k: v for k, v in kw.items() if v is not None}
    unknown = set(kw) - set(defaults)
    if unknown:
        raise TypeError(f"unknown preset parameter(s): {', '.join(sorted(unknown))}")
    out = dict(defaults)
    out.update(kw)
    return out


def _light_ring(n: int, radius: float, elevation_deg: float, intensity: float, world_up: str, azimuth0: float = 45.0):
    """`n` white point lights evenly in azimuth at `radius` from the origin and one elevation."""
    from pbrfit.physics.lights import point_light

    dirs = [environments.env_to_world(_yup_dir(elevation_deg, azimuth0 + 360.0 * k / n), world_up) for k in range(n)]
    return tuple(point_light(radius * d, (1.0, 1.0, 1.0), intensity) for d in dirs)


def _yup_dir(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit direction in the y-up frame, azimuth 0 towards +Z (the rigs' convention)."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])


def _peer_plane(seed: int, **kw) -> Scene:
    p = _common(kw, dict(size=128, views=6, noise=0.0, noise_model="gaussian", supersample=1, texture_size=64,
                         image_format="exr", distance=2.9, fov_deg=45.0, light_distance=2.6, light_intensity=6.0))
    rng = np.random.default_rng(seed)
    up = "+z"
    truth = textures.textured_maps(p["texture_size"], rng, metal="none", roughness_range=(0.15, 0.85))
    n = p["views"]
    elevations = np.where(np.arange(n) % 2 == 0, 50.0, 68.0)
    cams = rigs.orbit(n, p["distance"], elevations, world_up=up, azimuth_start_deg=15.0)
    lights = _light_ring(4, p["light_distance"], 55.0, p["light_intensity"], up)
    return Scene(
        name="peer-plane", seed=seed, mesh=meshes.plane(2.0, world_up=up), truth=truth, cameras=cams,
        camera_angle_x=math.radians(p["fov_deg"]), width=p["size"], height=p["size"], lights=lights,
        world_up=up, image_format=p["image_format"], supersample=p["supersample"], noise=p["noise"],
        noise_model=p["noise_model"], params=p,
    )  # fmt: skip


def _plane_flash(seed: int, **kw) -> Scene:
    p = _common(kw, dict(size=128, views=12, noise=0.01, noise_model="gaussian", supersample=2, texture_size=64,
                         image_format="png16", fov_deg=50.0, flash_intensity=3.5, lamp_intensity=5.0,
                         metal_color=textures.GOLD))
    from pbrfit.physics.lights import point_light

    rng = np.random.default_rng(seed)
    up = "+y"
    truth = textures.textured_maps(p["texture_size"], rng, metal="binary", metal_color=p["metal_color"],
                                   roughness_range=(0.2, 0.8))  # fmt: skip
    cams = rigs.handheld(p["views"], rng, world_up=up, distance=(2.0, 2.6), elevation_deg=(45.0, 80.0))
    lamps = (
        point_light((-1.8, 2.2, 1.0), (1.0, 0.92, 0.8), p["lamp_intensity"]),
        point_light((1.6, 2.6, -1.4), (0.85, 0.9, 1.0), p["lamp_intensity"]),
    )
    return Scene(
        name="plane-flash", seed=seed, mesh=meshes.plane(2.0, world_up=up), truth=truth, cameras=cams,
        camera_angle_x=math.radians(p["fov_deg"]), width=p["size"], height=p["size"], lights=lamps,
        flash=Flash((1.0, 1.0, 1.0), p["flash_intensity"], (0.03, 0.02, 0.0)), world_up=up,
        image_format=p["image_format"], supersample=p["supersample"], noise=p["noise"],
        noise_model=p["noise_model"], params=p,
    )  # fmt: skip


def _sphere_env(seed: int, **kw) -> Scene:
    p = _common(kw, dict(size=128, views=8, noise=0.0, noise_model="gaussian", supersample=1, texture_size=64,
                         image_format="exr", env_width=256, distance=3.5, fov_deg=40.0))
    rng = np.random.default_rng(seed)
    truth = textures.textured_maps(p["texture_size"], rng, metal="binary", metal_coverage=0.25)
    env = environments.sky(p["env_width"], p["env_width"] // 2, sun_elevation_deg=rng.uniform(25, 55),
                           sun_azimuth_deg=rng.uniform(-60, 60))  # fmt: skip
    cams = rigs.hemisphere(p["views"], p["distance"], min_elevation_deg=-10.0, max_elevation_deg=60.0, rng=rng)
    return Scene(
        name="sphere-env", seed=seed, mesh=meshes.uv_sphere(1.0, 96, 48), truth=truth, cameras=cams,
        camera_angle_x=math.radians(p["fov_deg"]), width=p["size"], height=p["size"], environment=env,
        image_format=p["image_format"], supersample=p["supersample"], noise=p["noise"],
        noise_model=p["noise_model"], params=p,
    )  # fmt: skip


def _atlas_tiles(rows: int, cols: int, texture_size: int):
    """uv rectangles of a rows x cols atlas, each inset by one texel so bilinear lookups stay inside."""
    inset = 1.0 / texture_size
    return [
        (c / cols + inset, r / rows + inset, (c + 1) / cols - inset, (r + 1) / rows - inset)
        for r in range(rows)
        for c in range(cols)
    ]


def _spheres_grid(seed: int, **kw) -> Scene:
    p = _common(kw, dict(size=192, views=6, noise=0.0, noise_model="gaussian", supersample=1, tile=8,
                         image_format="exr", metallic=(0.0, 0.25, 0.5, 0.75, 1.0),
                         roughness=(0.1, 0.3, 0.5, 0.7, 0.9), base_color=(0.8, 0.45, 0.2), spacing=1.0,
                         radius=0.4, distance=7.0, fov_deg=45.0, env_width=256, light_intensity=60.0,
                         texture_size=None))
    from pbrfit.physics.lights import point_light

    met, rough = tuple(p["metallic"]), tuple(p["roughness"])
    rows, cols = len(met), len(rough)
    if p["texture_size"] is not None:  # the chart's size: one tile per sphere
        p["tile"] = max(1, int(p["texture_size"]) // max(rows, cols))
    truth = textures.chart_maps(met, rough, tile=p["tile"], base_color=p["base_color"])
    tiles = _atlas_tiles(rows, cols, p["tile"] * max(rows, cols))
    spheres = []
    for r in range(rows):
        for c in range(cols):
            centre = (p["spacing"] * (c - (cols - 1) / 2), p["spacing"] * ((rows - 1) / 2 - r), 0.0)
            spheres.append(meshes.uv_sphere(p["radius"], 32, 16, center=centre))
    mesh = meshes.combine(spheres, tiles)
    cams = rigs.orbit(p["views"], p["distance"], np.linspace(0.0, 20.0, p["views"]), azimuth_start_deg=-25.0,
                      azimuth_span_deg=50.0)  # fmt: skip
    env = environments.studio(p["env_width"], p["env_width"] // 2)
    key = point_light((4.0, 5.0, 6.0), (1.0, 0.97, 0.92), p["light_intensity"])
    return Scene(
        name="spheres-grid", seed=seed, mesh=mesh, truth=truth, cameras=cams,
        camera_angle_x=math.radians(p["fov_deg"]), width=p["size"], height=p["size"], lights=(key,),
        environment=env, image_format=p["image_format"], supersample=p["supersample"], noise=p["noise"],
        noise_model=p["noise_model"], max_depth=INTERREFLECTION_DEPTH, params=p,
    )  # fmt: skip


def _mesh_env(seed: int, **kw) -> Scene:
    p = _common(kw, dict(size=128, views=10, noise=0.0, noise_model="gaussian", supersample=1, texture_size=64,
                         image_format="exr", shape="torus", mesh=None, distance=4.0, fov_deg=40.0, env_width=256,
                         metal="smooth"))
    rng = np.random.default_rng(seed)
    depth = MIN_DEPTH if p["mesh"] is None and p["shape"] in ("box", "sphere") else INTERREFLECTION_DEPTH  # convex?
    if p["mesh"] is not None:
        mesh = meshes.load_mesh(p["mesh"], normalize=True)
        p["mesh"] = str(p["mesh"])
    elif p["shape"] == "torus":
        mesh = meshes.torus(1.0, 0.4, 96, 48)
    elif p["shape"] == "box":
        mesh = meshes.rounded_box((1.6, 1.1, 1.1), 0.25)
    elif p["shape"] == "sphere":
        mesh = meshes.uv_sphere(1.0, 96, 48)
    else:
        raise ValueError(f"shape must be 'torus', 'box' or 'sphere', got {p['shape']!r}")
    truth = textures.textured_maps(p["texture_size"], rng, metal=p["metal"])
    env = environments.studio(p["env_width"], p["env_width"] // 2)
    cams = rigs.hemisphere(p["views"], p["distance"], min_elevation_deg=10.0, max_elevation_deg=70.0, rng=rng)
    return Scene(
        name="mesh-env", seed=seed, mesh=mesh, truth=truth, cameras=cams,
        camera_angle_x=math.radians(p["fov_deg"]), width=p["size"], height=p["size"], environment=env,
        image_format=p["image_format"], supersample=p["supersample"], noise=p["noise"],
        noise_model=p["noise_model"], max_depth=depth, params=p,
    )  # fmt: skip


def _demo(seed: int, **kw) -> Scene:
    p = _common(kw, dict(size=96, views=8, noise=0.005, noise_model="gaussian", supersample=1, texture_size=64,
                         image_format="exr", distance=4.0, fov_deg=45.0, env_width=128, light_intensity=12.0,
                         floor_size=3.0, sphere_radius=0.6))
    from pbrfit.physics.lights import point_light

    rng = np.random.default_rng(seed)
    n = p["texture_size"]
    truth = textures.textured_maps(n, rng, metal="binary", metal_coverage=0.25)
    r = p["sphere_radius"]
    inset = 1.0 / n
    floor = meshes.plane(p["floor_size"], segments=4)
    sphere = meshes.uv_sphere(r, 64, 32, center=(0.0, r, 0.0))
    mesh = meshes.combine([floor, sphere], [(inset, inset, 0.5 - inset, 1 - inset), (0.5 + inset, inset, 1 - inset, 1 - inset)])
    sun_el, sun_az = 40.0, 35.0
    env = environments.sky(p["env_width"], p["env_width"] // 2, sun_elevation_deg=sun_el, sun_azimuth_deg=sun_az)
    sun = environments.env_to_world(environments.direction_from_angles(sun_el, sun_az), "+y")
    light = point_light(4.0 * sun, (1.0, 0.96, 0.9), p["light_intensity"])
    cams = rigs.hemisphere(p["views"], p["distance"], target=(0.0, 0.3, 0.0), min_elevation_deg=20.0,
                           max_elevation_deg=65.0, rng=rng)  # fmt: skip
    return Scene(
        name="demo", seed=seed, mesh=mesh, truth=truth, cameras=cams, camera_angle_x=math.radians(p["fov_deg"]),
        width=p["size"], height=p["size"], lights=(light,), environment=env, image_format=p["image_format"],
        supersample=p["supersample"], noise=p["noise"], noise_model=p["noise_model"],
        max_depth=INTERREFLECTION_DEPTH, params=p,
    )  # fmt: skip


def _on_floor(name: str, seed: int, **kw) -> Scene:
    """``sphere-floor`` and ``torus-floor`` (module docstring)."""
    p = _common(kw, dict(size=96, views=12, noise=0.0, noise_model="gaussian", supersample=1, texture_size=64,
                         image_format="exr", distance=4.2, fov_deg=45.0, env_width=256, floor_size=3.2,
                         sun_elevation_deg=None, sun_azimuth_deg=None))
    rng = np.random.default_rng(seed)
    n = p["texture_size"]
    truth = textures.textured_maps(n, rng, metal="binary", metal_coverage=0.25)
    if name == "sphere-floor":
        obj = meshes.uv_sphere(0.6, 64, 32, center=(0.0, 0.6, 0.0))
    else:
        minor = 0.3
        obj = meshes.torus(0.8, minor, 96, 32).translated((0.0, minor, 0.0))
    inset = 1.0 / n
    floor = meshes.plane(p["floor_size"], segments=4)
    mesh = meshes.combine([floor, obj], [(inset, inset, 0.5 - inset, 1 - inset),
                                         (0.5 + inset, inset, 1 - inset, 1 - inset)])
    for key, low, high in (("sun_elevation_deg", 30.0, 50.0), ("sun_azimuth_deg", -60.0, 60.0)):
        if p[key] is None:
            p[key] = float(rng.uniform(low, high))
    env = environments.sky(p["env_width"], p["env_width"] // 2, sun_elevation_deg=p["sun_elevation_deg"],
                           sun_azimuth_deg=p["sun_azimuth_deg"])
    cams = rigs.hemisphere(p["views"], p["distance"], target=(0.0, 0.3, 0.0), min_elevation_deg=20.0,
                           max_elevation_deg=65.0, rng=rng)
    return Scene(
        name=name, seed=seed, mesh=mesh, truth=truth, cameras=cams, camera_angle_x=math.radians(p["fov_deg"]),
        width=p["size"], height=p["size"], environment=env, image_format=p["image_format"],
        supersample=p["supersample"], noise=p["noise"], noise_model=p["noise_model"],
        max_depth=INTERREFLECTION_DEPTH, params=p,
    )  # fmt: skip


#: name -> (builder(seed, **overrides) -> Scene, one-line description)
PRESETS: dict[str, tuple[Callable[..., Scene], str]] = {
    "peer-plane": (_peer_plane, "Z-up 2x2 plane, 6 views 128^2, 4 point lights, 64^2 maps, metallic 0 (the peer scene)"),
    "plane-flash": (_plane_flash, "floor under a phone flash on 12 cameras + 2 lamps, gold metal, 16-bit sRGB PNG"),
    "sphere-env": (_sphere_env, "textured sphere under a procedural sky, 8 views, EXR"),
    "spheres-grid": (_spheres_grid, "5x5 metallic x roughness chart of spheres, studio + key light"),
    "mesh-env": (_mesh_env, "torus (or box, or your mesh) under a studio environment, 10 views"),
    "demo": (_demo, "sphere on a floor under a sky and a light, textured truth, 8 views 96^2"),
    "sphere-floor": (functools.partial(_on_floor, "sphere-floor"),
                     "sphere resting on a textured floor under a sky with a sun alone, binary metal, 12 views"),
    "torus-floor": (functools.partial(_on_floor, "torus-floor"),
                    "torus lying on a textured floor under a sky with a sun alone, binary metal, 12 views"),
}


def preset_names() -> tuple[str, ...]:
    return tuple(PRESETS)


def describe_presets() -> str:
    return "\n".join(f"  {name:13s} {desc}" for name, (_, desc) in PRESETS.items())


def make_scene(name: str, seed: int = 0, **overrides) -> Scene:
    """Build preset `name` with `seed`; keyword overrides (None = the preset's default) include
    ``size``, ``views``, ``noise``, ``noise_model``, ``supersample``, ``texture_size`` (``tile``
    for spheres-grid), ``image_format`` and preset-specific ones (``shape``, ``mesh``...).
    Raises `pbrfit.errors.CaptureError` for an unknown preset or parameter."""
    from pbrfit.errors import CaptureError

    if name not in PRESETS:
        raise CaptureError(f"synth: unknown preset {name!r} (expected one of {', '.join(PRESETS)})")
    builder, _ = PRESETS[name]
    try:
        return builder(int(seed), **overrides)
    except TypeError as err:
        raise CaptureError(f"synth {name}: {err}") from None
