"""Relighting: a fit's maps and the truth's, path-traced by Mitsuba 3 under light the capture never had.

Both materials are rendered by `data_synth.mitsuba_render` (the same ``GltfBSDF``, the same path
integrator) on the capture's mesh under a new scene (`novel_scene`): the studio environment of
`data_synth.environments.studio` in place of the capture's, two coloured point lights, and new
cameras on the capture's orbit (its cameras' distance to the point they look at) at other
azimuths. The two renders use the same samples per pixel and independent seeds, so their
noise is independent and its share of the error is known: ``ceiling_db`` is the PSNR that this
noise alone leaves (each pixel's variance, from Mitsuba's passes, of both renders).

Scores (`scores`), over the pixels whose centre sees the mesh at a texel the fit observed
(coverage > 0; elsewhere the fit holds its prior and there is nothing to relight):

- per view, the truth render's 99.9th percentile over those pixels (all channels) is the peak: both
  images are clipped at it and divided by it; PSNR = -10 log10(mean squared difference), pooled
  over the views' pixels;
- ``raw``: the fitted render as it is; ``scaled``: after the per-channel scale s_c = Σ p r / Σ p²
  (least squares of the prediction p to the reference r, both clipped and divided by the peak,
  over the scored pixels of every view; the scaled prediction clipped again), as nvdiffrec and
  NeRFactor report relighting (a scale fitted to the unclipped values would serve the few
  highlights above the peak and lower the PSNR of the rest);
- per class: ``dielectric`` and ``metal`` are the pixels whose centre sees a texel (the texel the
  centre's uv falls in) of truth metallic < 0.5 and >= 0.5 (the presets' metallic is binary);
  ``all`` is every scored pixel.

    python experiments/relight.py CAPTURE FIT [--views 4] [--size 64] [--spp 4096] [--max-depth 4] [--seed 0]
                                  [--json OUT.json]

Needs the ``mitsuba`` extra and ``DRJIT_LIBLLVM_PATH`` (`data_synth.mitsuba_render.load_mitsuba`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

#: The percentile of the truth render's values each view is clipped at (the peak of its PSNR).
CLIP_PERCENTILE = 99.9
#: Truth metallic at or above this makes a texel metal, below it dielectric.
METAL_AT = 0.5
#: The new point lights: (offset from the mesh's centre in units of its bounding radius, in the
#: y-up frame; colour; intensity in candela per squared bounding radius).
LIGHTS = (((1.1, 1.3, 0.7), (1.0, 0.85, 0.7), 3.0), ((-1.2, 0.8, -0.9), (0.65, 0.8, 1.0), 2.0))
#: The new cameras' elevations (degrees) and the turn of their azimuths from the rig's.
ELEVATIONS = (25.0, 55.0)
AZIMUTH_OFFSET = 47.0


def _orbit(capture) -> tuple[np.ndarray, float, float]:
    """(target, distance, camera_angle_x) of the capture's cameras: the point nearest every
    camera's optical axis (least squares), their mean distance to it, their mean field of view."""
    a, b, fovs, eyes = np.zeros((3, 3)), np.zeros(3), [], []
    for frame in capture.frames:
        cam = frame.camera
        eye, fwd = cam.c2w[:3, 3], -cam.c2w[:3, 2]
        p = np.eye(3) - np.outer(fwd, fwd)
        a, b = a + p, b + p @ eye
        eyes.append(eye)
        fovs.append(2.0 * math.atan(0.5 * cam.width / cam.fx))
    target = np.linalg.lstsq(a, b, rcond=None)[0]
    return target, float(np.mean(np.linalg.norm(np.asarray(eyes) - target, axis=1))), float(np.mean(fovs))


def novel_scene(capture, views: int, size: int, max_depth: int, seed: int):
    """(`data_synth.presets.Scene`, `Environment`): the capture's mesh under the new light and
    cameras (module docstring), holding the capture's truth maps (`with_maps` swaps them)."""
    import jax.numpy as jnp

    from data_synth import environments, rigs
    from data_synth.meshes import MeshData
    from data_synth.presets import Scene
    from pbrfit.io.material_files import read_material
    from pbrfit.lighting.environment import Environment
    from pbrfit.physics.lights import point_light

    mesh = capture.mesh
    target, distance, fov = _orbit(capture)
    centre = 0.5 * (mesh.bounds[0] + mesh.bounds[1])
    radius = 0.5 * float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    up = capture.world_up
    lights = tuple(point_light(centre + radius * environments.env_to_world(np.asarray(offset), up), colour,
                               intensity * radius**2) for offset, colour, intensity in LIGHTS)
    cameras = rigs.hemisphere(views, distance, target, up, *ELEVATIONS, rng=np.random.default_rng(seed),
                              azimuth_offset_deg=AZIMUTH_OFFSET)
    radiance = environments.studio()
    scene = Scene(name="relight", seed=seed, mesh=MeshData(mesh.vertices, mesh.faces, mesh.vertex_normals,
                                                           np.asarray(mesh.visual.uv)[:, :2]),
                  truth=truth_maps(read_material(capture.truth_dir)), cameras=cameras, camera_angle_x=fov,
                  width=size, height=size, lights=lights, environment=radiance, world_up=up, renderer="mitsuba",
                  max_depth=max_depth)
    return scene, Environment(jnp.asarray(radiance), up)


def truth_maps(material):
    """A `pbrfit.physics.material.Material`'s maps as the `data_synth.textures.TruthMaps` a scene renders."""
    from data_synth.textures import TruthMaps

    return TruthMaps(*(np.asarray(getattr(material, k), np.float32) for k in ("base_color", "metallic", "roughness")))


def with_maps(scene, material, seed: int):
    """`scene` holding `material`'s maps (a `pbrfit.physics.material.Material`), its renders seeded by `seed`."""
    return scene.replace(truth=truth_maps(material), seed=seed)


def pixel_texels(scene, mesh) -> list:
    """Per view, (H, W, 2) int texel (row, column) of the truth maps that each pixel centre sees,
    -1 where the centre misses the mesh."""
    from data_synth.writer import frame_camera
    from pbrfit.scene.gbuffer import compute_gbuffer

    h, w = scene.truth.shape
    out = []
    for c2w in scene.cameras:
        g = compute_gbuffer(mesh, frame_camera(scene, c2w))
        uv = np.asarray(g.uv, np.float64)
        t = np.stack([np.floor(uv[..., 1] * h) % h, np.floor(uv[..., 0] * w) % w], -1).astype(np.int64)
        out.append(np.where(np.asarray(g.hit, bool)[..., None], t, -1))
    return out


def pixel_classes(texels: list, metallic: np.ndarray, observed: np.ndarray) -> list:
    """Per view, (H, W) int8: 1 metal, 0 dielectric (the truth `metallic` at the pixel's texel,
    `METAL_AT`), -1 not scored (misses the mesh, or the texel is not `observed`). `observed` is
    (h, w) bool at any resolution: a truth texel is observed where the texel of `observed` holding
    its centre is."""
    hm, wm = metallic.shape[:2]
    ho, wo = observed.shape
    out = []
    for t in texels:
        r, c = np.maximum(t[..., 0], 0), np.maximum(t[..., 1], 0)
        seen = observed[(r * ho) // hm, (c * wo) // wm] & (t[..., 0] >= 0)
        metal = metallic[r, c, 0] >= METAL_AT
        out.append(np.where(seen, metal.astype(np.int8), np.int8(-1)))
    return out


def scores(reference, prediction, classes) -> dict:
    """PSNR of `prediction` against `reference` (`data_synth.mitsuba_render.MitsubaViews`) over the
    pixels of `classes` (`pixel_classes`), raw and scaled, per class; see the module docstring."""
    keep = [c >= 0 for c in classes]
    peaks = [np.percentile(r[k], CLIP_PERCENTILE) for r, k in zip(reference.radiance, keep)]
    clip = lambda x, peak: np.minimum(np.asarray(x, np.float64), peak) / peak  # noqa: E731
    ref = [clip(r, peak) for r, peak in zip(reference.radiance, peaks)]
    pred = [clip(p, peak) for p, peak in zip(prediction.radiance, peaks)]
    r_all = np.concatenate([r[k] for r, k in zip(ref, keep)])
    p_all = np.concatenate([p[k] for p, k in zip(pred, keep)])
    scale = np.sum(p_all * r_all, 0) / np.maximum(np.sum(p_all * p_all, 0), 1e-30)
    out = dict(scale=scale.tolist(), clip_percentile=CLIP_PERCENTILE)
    for name, want in (("all", (0, 1)), ("dielectric", (0,)), ("metal", (1,))):
        sq = {"raw": [], "scaled": [], "noise": []}
        for r, p, se_r, se_p, c, peak in zip(ref, pred, reference.stderr, prediction.stderr, classes, peaks):
            m = np.isin(c, want)
            sq["raw"].append((p[m] - r[m]) ** 2)
            sq["scaled"].append((np.minimum(p[m] * scale, 1.0) - r[m]) ** 2)
            sq["noise"].append((np.square(se_r[m], dtype=np.float64) + np.square(se_p[m], dtype=np.float64)) / peak**2)
        pixels = int(sum(len(s) for s in sq["raw"]))
        db = {k: float(-10.0 * np.log10(np.mean(np.concatenate(v)))) if pixels else float("nan") for k, v in sq.items()}
        out[name] = dict(pixels=pixels, raw_db=db["raw"], scaled_db=db["scaled"], ceiling_db=db["noise"])
    return out


@dataclasses.dataclass
class Relighting:
    """The new scene of a capture and its truth render, to score fits of the capture against."""

    scene: object
    environment: object
    mesh: object
    texels: list
    truth: object
    spp: int
    seconds: float

    @classmethod
    def prepare(cls, capture, views: int = 4, size: int = 64, spp: int = 4096, max_depth: int = 4, seed: int = 0):
        from data_synth.mitsuba_render import render_views

        scene, env = novel_scene(capture, views, size, max_depth, seed)
        texels = pixel_texels(scene, capture.mesh)
        t = time.perf_counter()
        truth = render_views(scene, capture.mesh, env, [x[..., 0] >= 0 for x in texels], spp)
        return cls(scene, env, capture.mesh, texels, truth, truth.spp, time.perf_counter() - t)

    def score(self, fit_dir, keep=None) -> dict:
        """Render the material of the fit output folder `fit_dir` and score it (`scores`); `keep`: a
        ``.npz`` file to write both renders and the pixels' classes to."""
        from data_synth.mitsuba_render import render_views
        from pbrfit.io.images import read_image
        from pbrfit.io.material_files import read_material

        fit_dir = Path(fit_dir)
        material = read_material(fit_dir)
        observed = read_image(fit_dir / "coverage.exr")[0][..., 0] > 0
        classes = pixel_classes(self.texels, self.scene.truth.metallic, observed)
        t = time.perf_counter()
        pred = render_views(with_maps(self.scene, material, self.scene.seed + 1), self.mesh, self.environment,
                            [c >= 0 for c in classes], self.spp)
        out = scores(self.truth, pred, classes)
        if keep is not None:
            np.savez_compressed(keep, truth=np.stack(self.truth.radiance), truth_se=np.stack(self.truth.stderr),
                                fit=np.stack(pred.radiance), fit_se=np.stack(pred.stderr), classes=np.stack(classes))
        hit = sum(int(np.sum(x[..., 0] >= 0)) for x in self.texels)
        out.update(render_s=time.perf_counter() - t, unobserved_share=1.0 - out["all"]["pixels"] / max(hit, 1),
                   noise=dict(truth=self.truth.noise, fit=pred.noise))
        return out

    def describe(self) -> dict:
        s = self.scene
        return dict(views=s.num_views, size=s.width, spp=self.spp, max_depth=int(s.max_depth), seed=int(s.seed),
                    environment="data_synth.environments.studio()", truth_render_s=self.seconds,
                    lights=[dict(position=np.asarray(x.position).tolist(), color=np.asarray(x.color).tolist(),
                                 intensity=float(x.intensity)) for x in s.lights])


def main(argv=None):
    from pbrfit.scene.capture import load_capture

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path, help="a capture folder with truth/")
    ap.add_argument("fit", type=Path, help="a fit's output folder (pbrfit fit --out)")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4096, help="samples per pixel of both renders")
    ap.add_argument("--max-depth", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="write the scores here")
    args = ap.parse_args(argv)
    capture = load_capture(args.capture)
    if capture.truth_dir is None:
        ap.error(f"{args.capture}: no truth/ folder to relight")
    relight = Relighting.prepare(capture, args.views, args.size, args.spp, args.max_depth, args.seed)
    result = dict(setup=relight.describe(), **relight.score(args.fit))
    for name in ("all", "dielectric", "metal"):
        r = result[name]
        print(f"{name:10s} {r['pixels']:6d} px  PSNR raw {r['raw_db']:5.1f} dB  scaled {r['scaled_db']:5.1f} dB  "
              f"(noise ceiling {r['ceiling_db']:.1f} dB)")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
