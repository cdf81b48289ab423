"""Image-based lighting: split sum and per-pixel integrals against Monte Carlo, and their cost, per knob setting.

Spheres of every roughness × metallic in a grid, seen orthographically from two sides of a sky
with a sun (front-lit and back-lit, so the sun's highlight and the grazing rim both appear), are
shaded by the split sum at several `IBLSettings` and by `monte_carlo_radiance` at a high sample
count, the reference. Reported per setting: build time (once per environment), shading time,
relative RMS error over all pixels, and relative mean absolute error per n·v band (grazing is
where the split sum's N = V = R assumption fails). Monte Carlo itself at lower sample counts is
on the same chart, for the trade the split sum makes, and so are the per-pixel lobe integrals
of `pbrfit.lighting.pixel_ibl` (what ``pbrfit fit --ibl per_pixel`` uses) at several `PixelIBLSettings`:
their "build" is the precomputation for every point, their shading the lookup.

    python experiments/ibl_accuracy.py [--env sky.exr] [--quick]

Writes experiments/results/ibl_accuracy.json and .png. Runs in 10 minutes on 2 cores, most of it in the
per-pixel rows (`--quick`: half a minute).
"""

from __future__ import annotations

import os

# jaxlib 0.10.2 miscompiles some reductions on the CPU (jax-ml/jax#39103); pbrfit's IBL code
# avoids the pattern, this keeps the rest of the BRDF code out of it too.
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_experimental_ynn_fusion_type=-reduce").strip()

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from pbrfit.lighting.environment import load_environment, procedural_sky  # noqa: E402
from pbrfit.lighting.ibl import IBLSettings, build_ibl, shade_ibl  # noqa: E402
from pbrfit.physics.model import Model  # noqa: E402
from pbrfit.lighting.montecarlo import monte_carlo_radiance  # noqa: E402
from pbrfit.lighting.pixel_ibl import PixelIBLSettings, pixel_ibl, shade_pixel_ibl  # noqa: E402

ROUGHNESS = (0.05, 0.15, 0.3, 0.5, 0.75, 1.0)
METALLIC = (0.0, 1.0)
BASE_COLOR = (0.9, 0.6, 0.3)
SUN_AZIMUTH, SUN_ELEVATION = 40.0, 30.0
VIEWS = {"front-lit": SUN_AZIMUTH + 180.0, "back-lit": SUN_AZIMUTH}   # camera looks towards this azimuth
BANDS = ((0.0, 0.1), (0.1, 0.3), (0.3, 0.6), (0.6, 1.0))
DEFAULT = IBLSettings()

SETTINGS = {
    "minimal": IBLSettings(lut_size=16, lut_samples=64, prefilter_levels=4, prefilter_resolution=32,
                           prefilter_samples=16, irradiance="sh9", env_resolution=64),
    "fast": IBLSettings(lut_size=32, lut_samples=256, prefilter_levels=5, prefilter_resolution=64,
                        prefilter_samples=32, irradiance="sh9", env_resolution=128),
    "default": DEFAULT,
    "default, SH9 irradiance": dataclasses.replace(DEFAULT, irradiance="sh9"),
    "default, reflect direction": dataclasses.replace(DEFAULT, specular_direction="reflect"),
    "default, SH9 + reflect (Karis)": dataclasses.replace(DEFAULT, irradiance="sh9", specular_direction="reflect"),
    "default, LUT 16/128": dataclasses.replace(DEFAULT, lut_size=16, lut_samples=128),
    "default, 16 prefilter samples": dataclasses.replace(DEFAULT, prefilter_samples=16),
    "default, 256 prefilter samples": dataclasses.replace(DEFAULT, prefilter_samples=256),
    "default, 9 levels": dataclasses.replace(DEFAULT, prefilter_levels=9),
    "default, no FIS (lod bias -8)": dataclasses.replace(DEFAULT, prefilter_lod_bias=-8.0),
    "default, lod bias 0": dataclasses.replace(DEFAULT, prefilter_lod_bias=0.0),
    "high": IBLSettings(lut_size=64, lut_samples=1024, prefilter_levels=9, prefilter_resolution=256,
                        prefilter_samples=256, irradiance="map", irradiance_resolution=32, env_resolution=256),
}


PIXEL_SETTINGS = {f"{levels} levels, {samples} samples": PixelIBLSettings(levels=levels, samples=samples)
                  for levels, samples in ((9, 32), (9, 128), (17, 32), (17, 128), (17, 512), (33, 128))}


def sphere_points(res: int):
    """Normals on the visible hemisphere of a sphere seen from each view (camera 10° above the
    horizon), stratified uniformly in n·v ∈ (0, 1) and in azimuth about the view axis: every n·v
    band gets the same number of points (an image would hold few grazing ones)."""
    c = (np.arange(res) + 0.5) / res                       # n·v strata
    phi = (np.arange(2 * res) + 0.5) / (2 * res) * 2 * np.pi
    cc, pp = np.meshgrid(c, phi, indexing="ij")
    ss = np.sqrt(1 - cc * cc)
    n_cam = np.stack([ss * np.cos(pp), ss * np.sin(pp), cc], -1).reshape(-1, 3)
    ns, vs, names = [], [], []
    for name, az in VIEWS.items():
        a, e = math.radians(az), math.radians(10.0)
        fwd = np.array([math.cos(e) * math.sin(a), math.sin(e), -math.cos(e) * math.cos(a)])   # look direction
        right = np.cross(fwd, [0, 1, 0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        ns.append(n_cam[:, :1] * right + n_cam[:, 1:2] * up + n_cam[:, 2:3] * (-fwd))
        vs.append(np.broadcast_to(-fwd, ns[-1].shape))
        names += [name] * len(n_cam)
    return np.concatenate(ns), np.concatenate(vs), np.array(names)


def make_scene(res: int):
    n, v, view = sphere_points(res)
    k = len(n)
    rows = [(r, m) for m in METALLIC for r in ROUGHNESS]
    f = lambda a: jnp.asarray(a, jnp.float32)
    return dict(
        n=f(np.tile(n, (len(rows), 1))), v=f(np.tile(v, (len(rows), 1))),
        base=f(np.tile(BASE_COLOR, (k * len(rows), 1))),
        metallic=f(np.repeat([m for _, m in rows], k)[:, None]),
        roughness=f(np.repeat([r for r, _ in rows], k)[:, None]),
        view=np.tile(view, len(rows)), n_dot_v=np.tile(np.sum(n * v, -1), len(rows)), rows=rows, per_sphere=k)


def timed(fn, repeats=1):
    """(result, seconds of the fastest warm run): the first call compiles and is not counted."""
    out = jax.block_until_ready(fn())
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t)
    return out, best


def errors(est: np.ndarray, ref: np.ndarray, scene) -> dict:
    """Error of an estimate against the reference, every pixel and channel weighted alike.

    rel_mae = mean |d| / mean ref (the headline: L1, so a sun's highlight counts by its energy
    without swamping everything as a square would); rel_rmse likewise with squares; p90_rel: 90th
    percentile of the per-pixel |d| / (ref + 1% of the mean); and rel_mae per n·v band and per sphere.
    """
    d = est - ref
    floor = 0.01 * np.mean(ref)
    out = {"rel_mae": float(np.mean(np.abs(d)) / np.mean(ref)),
           "rel_rmse": float(np.sqrt(np.mean(d * d)) / np.mean(ref)),
           "p90_rel": float(np.percentile(np.abs(d) / (ref + floor), 90))}
    nv = scene["n_dot_v"]
    out["rel_mae_by_n_dot_v"] = {f"{lo:.1f}-{hi:.1f}": float(np.mean(np.abs(d[(nv >= lo) & (nv < hi)]))
                                                            / np.mean(ref[(nv >= lo) & (nv < hi)]))
                                 for lo, hi in BANDS}
    k = scene["per_sphere"]
    out["rel_mae_by_sphere"] = {f"r={r:g} m={m:g}": float(np.mean(np.abs(d[i * k:(i + 1) * k]))
                                                          / np.mean(ref[i * k:(i + 1) * k]))
                                for i, (r, m) in enumerate(scene["rows"])}
    return out


ENV_STYLE = {"sun": ("o", "-"), "overcast": ("^", "--")}


def plot(results, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(14, 5.6))
    for env_name, res in results["environments"].items():
        marker, ls = ENV_STYLE.get(env_name, ("o", "-"))
        for name, r in res["split_sum"].items():
            t = r["build_s"] + r["shade_s"]
            e = r["error"]["rel_mae"]
            ax.scatter(t, e, marker=marker, color="C3" if name == "default" else "C0", zorder=3)
            if env_name == "sun":
                ax.annotate(name, (t, e), fontsize=6.5, xytext=(4, 2), textcoords="offset points")
        for name, r in res.get("per_pixel", {}).items():
            t = r["build_s"] + r["shade_s"]
            e = r["error"]["rel_mae"]
            ax.scatter(t, e, marker=marker, color="C4", zorder=3)
            if env_name == "sun":
                ax.annotate(name, (t, e), fontsize=6.5, xytext=(4, 2), textcoords="offset points", color="C4")
        mc = res["monte_carlo"]
        ax.plot([m["time_s"] for m in mc], [m["error"]["rel_mae"] for m in mc], marker=marker, ls=ls, color="C2",
                label=f"Monte Carlo ({env_name})")
        for m in mc:
            ax.annotate(f'{m["samples"]}', (m["time_s"], m["error"]["rel_mae"]), fontsize=6.5, xytext=(4, -9),
                        textcoords="offset points")
        ax.axhline(res["reference"]["noise_rel_mae"], color="0.5", lw=0.8, ls=ls, label=f"reference noise ({env_name})")
        for name in ("default", "fast", "high"):
            if name in res["split_sum"]:
                ys = list(res["split_sum"][name]["error"]["rel_mae_by_n_dot_v"].values())
                bx.plot(np.arange(len(ys)), ys, marker=marker, ls=ls, lw=2.2 if name == "default" else 1,
                        label=f"{name} ({env_name})", color={"default": "C3", "fast": "C0", "high": "C1"}[name])
    ax.scatter([], [], marker="o", color="C0", label="split sum, sky with sun (red: default)")
    ax.scatter([], [], marker="^", color="C0", label="split sum, overcast sky")
    ax.scatter([], [], marker="o", color="C4", label="per-pixel integrals (precompute + shade)")
    ax.set(xscale="log", yscale="log", xlabel="seconds, warm (split sum: build + shade; per pixel: integrate + shade; Monte Carlo: render)",
           ylabel="relative mean absolute error vs reference",
           title=f'{results["points"]} sphere points, {len(ROUGHNESS)} roughness × {len(METALLIC)} metallic')
    ax.legend(fontsize=7, loc="lower left")
    bx.set(xticks=np.arange(len(BANDS)), xticklabels=[f"{lo}–{hi}" for lo, hi in BANDS], yscale="log",
           xlabel="n·v band", ylabel="relative mean absolute error", title="split-sum error by viewing angle")
    bx.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def run_environment(env, scene, settings, ref_spp, mc_spp, model, pixel_settings):
    pts = (scene["n"], scene["v"], scene["base"], scene["metallic"], scene["roughness"])
    t0 = time.perf_counter()
    # Reference: two independent runs, so its own noise is measured.
    halves = [np.asarray(monte_carlo_radiance(env, *pts, model, ref_spp, jax.random.PRNGKey(1000 + k)))
              for k in range(2)]
    ref = 0.5 * (halves[0] + halves[1])
    noise = float(np.mean(np.abs(0.5 * (halves[0] - halves[1]))) / np.mean(ref))   # rel. MAE of the mean
    print(f"  reference: {4 * ref_spp} samples per point (2 runs × {ref_spp} steps × 2 strategies), "
          f"relative noise {noise:.2e}, {time.perf_counter() - t0:.0f} s")
    split = {}
    for name, s in settings.items():
        tables, build_s = timed(lambda: build_ibl(env, s))
        img, shade_s = timed(lambda: shade_ibl(tables, *pts, model), repeats=3)
        split[name] = dict(settings=dataclasses.asdict(s), build_s=build_s, shade_s=shade_s,
                           error=errors(np.asarray(img), ref, scene))
        e = split[name]["error"]
        print(f"  {name:31s} build {build_s:7.3f} s  shade {shade_s:7.4f} s  rel MAE {e['rel_mae']:.4f}"
              f"  by n·v {[round(x, 4) for x in e['rel_mae_by_n_dot_v'].values()]}")
    per_pixel = {}
    for name, s in pixel_settings.items():
        tables, build_s = timed(lambda: pixel_ibl(env, np.asarray(pts[0]), np.asarray(pts[1]), model, s))
        img, shade_s = timed(lambda: shade_pixel_ibl(tables, *pts[2:], model), repeats=3)
        per_pixel[name] = dict(settings=dataclasses.asdict(s), build_s=build_s, shade_s=shade_s,
                               error=errors(np.asarray(img), ref, scene))
        e = per_pixel[name]["error"]
        print(f"  per-pixel {name:21s} build {build_s:7.3f} s  shade {shade_s:7.4f} s  rel MAE {e['rel_mae']:.4f}"
              f"  by n·v {[round(x, 4) for x in e['rel_mae_by_n_dot_v'].values()]}")
    mc = []
    for spp in mc_spp:
        est, sec = timed(lambda: monte_carlo_radiance(env, *pts, model, spp, jax.random.PRNGKey(7)))
        mc.append(dict(samples=2 * spp, time_s=sec, error=errors(np.asarray(est), ref, scene)))
        print(f"  Monte Carlo {2 * spp:5d} samples {sec:7.3f} s  rel MAE {mc[-1]['error']['rel_mae']:.4f}")
    return dict(reference=dict(samples_per_point=4 * ref_spp, noise_rel_mae=noise), split_sum=split,
                per_pixel=per_pixel, monte_carlo=mc)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", type=Path, help="equirect HDR to use instead of the procedural skies")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    ap.add_argument("--quick", action="store_true", help="fewer points, settings and samples (a smoke run)")
    args = ap.parse_args(argv)

    sky = dict(sun_elevation_deg=SUN_ELEVATION, sun_azimuth_deg=SUN_AZIMUTH, sun_radius_deg=2.0)
    envs = ({"file": load_environment(args.env)} if args.env else
            {"sun": procedural_sky(256, sun_illuminance=8.0, **sky),
             "overcast": procedural_sky(256, sun_illuminance=0.0, **sky)})
    scene = make_scene(6 if args.quick else 16)
    settings = {"default": DEFAULT, "minimal": SETTINGS["minimal"]} if args.quick else SETTINGS
    model = Model()
    t0 = time.perf_counter()
    out = {}
    for name, env in envs.items():
        print(f"environment: {name}")
        pixel_settings = {"9 levels, 32 samples": PIXEL_SETTINGS["9 levels, 32 samples"]} if args.quick else PIXEL_SETTINGS
        out[name] = run_environment(env, scene, settings, 128 if args.quick else 1024,
                                    (8, 32) if args.quick else (8, 32, 128), model, pixel_settings)
    results = dict(
        description=__doc__.splitlines()[0],
        environments_used=(str(args.env) if args.env else
                           "procedural_sky(256, sun 2° radius, sun_illuminance 8 / 0), sun at 30° elevation"),
        points=int(scene["n"].shape[0]), roughness=ROUGHNESS, metallic=METALLIC, base_color=BASE_COLOR,
        views=VIEWS, model=model.describe(), n_dot_v_bands=BANDS, environments=out,
        default=dataclasses.asdict(DEFAULT),
        machine=dict(cpu_count=os.cpu_count(), platform=platform.platform(), jax=jax.__version__),
        total_s=time.perf_counter() - t0, quick=args.quick)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "ibl_accuracy_quick" if args.quick else "ibl_accuracy"
    (args.out / f"{stem}.json").write_text(json.dumps(results, indent=1))
    plot(results, args.out / f"{stem}.png")
    print(f"wrote {args.out / stem}.json/.png in {results['total_s']:.0f} s")


if __name__ == "__main__":
    main()
