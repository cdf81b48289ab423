"""Fits of path-traced captures: sphere and torus on a floor, rendered by Mitsuba 3, fitted four ways.

Per scene (data_synth's ``sphere-floor`` and ``torus-floor``, seed 0) and per ``max_depth`` (2:
direct light only; 4: with light reflected between surfaces), the capture is rendered by
Mitsuba's path tracer (`data_synth.mitsuba_render`, a fixed sample count) and given Gaussian noise
of std ``--noise`` times the mean linear pixel value over the mesh (every view's masked pixels
pooled; `add_noise`): not ``pbrfit synth --noise``, whose std is absolute (at a display value of 1).
Each capture is fitted (`pbrfit.cli.fit.run_fit`, the maps at the truth's size) with `CONFIGS`:
the default (what plain ``pbrfit fit`` picks: ``--ibl auto``, the split sum, then per-pixel integrals
with occlusion auto where its residuals show light it cannot model, `pbrfit.fitting.stages.ibl`),
the split sum with occlusion, the per-pixel integrals without and with occlusion. Per fit:

- per map, the RMSE over the texels the fit is sure of (σ ≤ `pbrfit.cli.demo.CONFIDENT_SIGMA` in
  every channel of the map, as ``pbrfit demo`` counts them: `recovery_table`), over all observed
  texels and over the well-observed ones (`solvers._metrics`), and the share of observed texels
  within 2σ;
- relighting PSNR (`relight.Relighting`): the fitted and the true maps path-traced under a studio
  environment and two point lights from four new views, raw and scaled, dielectric and metal;
- the fit's wall time and the occlusion's and per-pixel integrals' share of it.

Finally `pathtraced.png`: per scene, each texel's base-colour error of the per-pixel fits without
and with occlusion (max_depth 4), and what occlusion changes.

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
    python experiments/pathtraced.py [--scenes sphere-floor torus-floor] [--depths 2 4] [--size 48] [--views 12]
                                     [--texture-size 32] [--spp 16384] [--noise 0.01] [--extras] [--work DIR]

Then ``--centres --work DIR`` adds the probe of the pixel footprint (`run_centres`): the first
scene's max_depth 2 capture rendered at pixel centres.

Writes experiments/results/pathtraced.json (after every fit) and pathtraced.png; ``--tables``
prints the tables of experiments/pathtraced.md from the JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

sys.path.insert(0, str(Path(__file__).parent))
from relight import Relighting  # noqa: E402
from solvers import _metrics, machine  # noqa: E402

#: name: fit options (`pbrfit.FitOptions` fields) besides the resolution.
CONFIGS = {
    "default": {},
    "split_sum + occlusion": dict(ibl="split_sum", occlusion="on"),
    "per_pixel": dict(ibl="per_pixel", occlusion="off"),
    "per_pixel + occlusion": dict(ibl="per_pixel", occlusion="on", occlusion_settings=dict(bounce="off")),
}
#: Probes of the largest remaining error, on the max_depth 4 captures after every `CONFIGS` fit
#: (``--extras``): the pixel footprint (Mitsuba's pixel is the mean over its area, the default fit
#: of a linear capture shades the pixel centre), the resolution of the occlusion's direction cells,
#: and the light reflected between surfaces (the bounce, chosen by default: forced on and off, at pixel centres).
EXTRAS = {
    "per_pixel + occlusion, 2 × 2 pixel samples": dict(ibl="per_pixel", occlusion="on", pixel_samples=2,
                                                        occlusion_settings=dict(bounce="off")),
    "per_pixel + occlusion, 32-row cells": dict(ibl="per_pixel", occlusion="on",
                                                occlusion_settings=dict(rows=32, bounce="off")),
    "per_pixel + occlusion + bounce, pixel centres": dict(ibl="per_pixel", occlusion="on", pixel_samples=1,
                                                          occlusion_settings=dict(bounce="on")),
    "per_pixel + occlusion, pixel centres": dict(ibl="per_pixel", occlusion="on", pixel_samples=1,
                                                 occlusion_settings=dict(bounce="off")),
    "per_pixel + occlusion + bounce, 3 × 3 pixel samples": dict(ibl="per_pixel", occlusion="on", pixel_samples=3,
                                                                occlusion_settings=dict(bounce="on")),
}
#: The seed of every scene, and of the noise added (with the scene's name and depth).
SEED = 0


def synthesize_capture(name: str, depth: int, out: Path, args) -> dict:
    """Render the capture with Mitsuba (no noise yet); what ``truth/synth.json`` says of the renderer."""
    from data_synth.writer import synthesize

    scene = make_scene_for(name, args)
    result = synthesize(scene.replace(renderer="mitsuba", max_depth=depth, spp=args.spp), out,
                        write_contact_sheet=False)
    return dict(result.renderer, seconds=result.seconds)


def centre_sampled_capture(name: str, depth: int, like: Path, out: Path, args) -> dict:
    """The capture `like` with each pixel's value at its centre instead of its area's mean: Mitsuba
    renders 3 x 3 sub-pixels per pixel (``--centre-spp`` each) and the middle one, whose centre is the
    pixel's, is kept (a ninth of the pixel's area). The masks and everything else are `like`'s."""
    import shutil

    from data_synth.writer import synthesize
    from pbrfit.io.images import write_image
    from pbrfit.scene.capture import load_capture

    fine = out.with_name(out.name + "-3x")
    scene = make_scene_for(name, args, size=3 * args.size)
    result = synthesize(scene.replace(renderer="mitsuba", max_depth=depth, spp=args.centre_spp), fine,
                        write_contact_sheet=False)
    shutil.copytree(like, out)
    capture = load_capture(out)
    for frame, image in zip(capture.frames, result.clean):
        write_image(capture.root / capture.raw["frames"][frame.index]["file_path"],
                    np.ascontiguousarray(image[1::3, 1::3]), "float")
    shutil.rmtree(fine)
    return dict(result.renderer, seconds=result.seconds)


def make_scene_for(name: str, args, **changes):
    from data_synth.presets import make_scene

    sizes = dict(size=args.size, views=args.views, texture_size=args.texture_size, noise=0.0)
    return make_scene(name, SEED, **dict(sizes, **changes))


def add_noise(capture_dir: Path, relative: float, seed) -> dict:
    """Add N(0, s²) to every image of the capture (linear EXR), s = `relative` × the mean linear value
    of the masked pixels of every view (all channels); returns s and that mean."""
    from data_synth.noise import gaussian
    from pbrfit.io.images import write_image
    from pbrfit.scene.capture import load_capture

    capture = load_capture(capture_dir)
    mean = float(np.mean(np.concatenate([np.asarray(f.image)[f.mask].ravel() for f in capture.frames]), dtype=np.float64))
    std = relative * mean
    rng = np.random.default_rng(seed)
    for frame in capture.frames:
        write_image(capture.root / capture.raw["frames"][frame.index]["file_path"],
                    gaussian(np.asarray(frame.image, np.float32), std, rng), "float")
    return dict(std=std, mean=mean, relative=relative)


def fit_row(capture, truth, out: Path, options: dict, texture_size: int, cache: Path, relight) -> dict:
    """Fit `capture` into `out` and measure the fit (module docstring)."""
    from pbrfit.cli.demo import CONFIDENT_SIGMA, recovery_table
    from pbrfit.cli.fit import run_fit
    from pbrfit.fitting.options import FitOptions

    from pbrfit.lighting.visibility import OcclusionSettings

    if "occlusion_settings" in options:
        options = dict(options, occlusion_settings=OcclusionSettings(**options["occlusion_settings"]))
    result, _ = run_fit(capture, out, FitOptions(resolution=texture_size, **options), cache_dir=cache, quiet=True)
    sigma = np.asarray(result.uncertainty)[..., :5]
    report = result.report
    return dict(
        sure={r["map"]: dict(texels=r["confident"], rmse=r["rmse_confident"], rmse_all=r["rmse"],
                             median_sigma=r["median_sigma"], within_2sigma=r["within_2sigma"])
              for r in recovery_table(result.material, truth, sigma, result.coverage)},
        sure_sigma=CONFIDENT_SIGMA, observed=int(np.sum(np.asarray(result.coverage) > 0)),
        **_metrics(truth, result.material, result.coverage, sigma),
        relight=relight.score(out, keep=out.with_name(out.name + "-relight.npz")),
        wall_s=report["wall_time"], occlusion=report.get("occlusion"), ibl=report.get("ibl"),
        final_loss=report["final_loss"], psnr_fit=float(np.mean(report["psnr"])),
        pixel_samples=report.get("pixel_samples", 1), footprint=report.get("footprint"),
    )


def picture(work: Path, scenes, depth: int, out: Path) -> None:
    """Per scene: |base-colour error| per texel (mean over RGB) of the per-pixel fits without and
    with occlusion, and their difference (red: occlusion lowers the error)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pbrfit.fitting.result import truth_at
    from pbrfit.io.images import read_image
    from pbrfit.io.material_files import read_material

    fig, axes = plt.subplots(len(scenes), 3, figsize=(11, 3.6 * len(scenes)), squeeze=False)
    for row, name in zip(axes, scenes):
        cap = work / f"{name}-d{depth}"
        errs = []
        for config in ("per_pixel", "per_pixel + occlusion"):
            fit_dir = work / f"{name}-d{depth}-{_slug(config)}"
            fitted = read_material(fit_dir)
            truth = truth_at(read_material(cap / "truth"), fitted.resolution)
            seen = read_image(fit_dir / "coverage.exr")[0][..., 0] > 0
            e = np.abs(np.asarray(fitted.base_color) - np.asarray(truth.base_color)).mean(-1)
            errs.append(np.where(seen, e, np.nan))
        panels = (("occlusion off", errs[0], "magma", 0, 0.2), ("occlusion on", errs[1], "magma", 0, 0.2),
                  ("off − on", errs[0] - errs[1], "RdBu_r", -0.15, 0.15))
        for ax, (title, img, cmap, lo, hi) in zip(row, panels):
            im = ax.imshow(img, cmap=plt.get_cmap(cmap).with_extremes(bad="0.6"), vmin=lo, vmax=hi, interpolation="nearest")
            ax.set_title(f"{name}, max_depth {depth}: {title}", fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
            fig.colorbar(im, ax=ax, fraction=0.046)
    fig.suptitle("per-texel |base colour error| (mean of R, G, B), per-pixel IBL; left half of each map: "
                 "the floor, right half: the object; grey: unobserved", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def _slug(config: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in config)


def _fit(results: dict, args, name: str, depth: int, config: str, options: dict, relight, capture: str = "") -> None:
    """Fit the capture ``WORK/NAME-dDEPTH[-CAPTURE]`` with `options`, add its row to `results`, save them."""
    from pbrfit.io.material_files import read_material
    from pbrfit.scene.capture import load_capture

    cap_dir = args.work / "-".join(filter(None, (f"{name}-d{depth}", capture)))
    row = fit_row(load_capture(cap_dir), read_material(cap_dir / "truth"), cap_dir.with_name(f"{cap_dir.name}-{_slug(config)}"),
                  options, args.texture_size, args.work / "cache", relight)
    results["fits"].append(dict(scene=name, max_depth=depth, config=config, capture=capture or "pixel area", **row))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "pathtraced.json").write_text(json.dumps(results, indent=1))
    print(f"  {name} d{depth} {config:22s} {_line(row)}", flush=True)


def run_refit(args) -> None:
    """``--refit CONFIG ...``: fit an earlier run's captures (``--work``, the ``--scenes`` at the
    ``--depths``) again with those `CONFIGS` or `EXTRAS` (the code as it is now), each row replacing the
    earlier row of its scene, depth and config in pathtraced.json."""
    from pbrfit.scene.capture import load_capture

    results = json.loads((args.out / "pathtraced.json").read_text())
    for name in args.scenes:
        relight = None
        for depth in args.depths:
            cap_dir = args.work / f"{name}-d{depth}"
            relight = relight or Relighting.prepare(load_capture(cap_dir), args.relight_views, args.relight_size,
                                                    args.relight_spp)
            for config in args.refit:
                same = [i for i, f in enumerate(results["fits"]) if (f["scene"], f["max_depth"], f["config"],
                        f.get("capture", "pixel area")) == (name, depth, config, "pixel area")]
                _fit(results, args, name, depth, config, dict(CONFIGS, **EXTRAS)[config], relight)
                if same:  # in the earlier row's place
                    results["fits"][same[0]] = results["fits"].pop()
                    (args.out / "pathtraced.json").write_text(json.dumps(results, indent=1))


def _capture(results: dict, args, name: str, depth: int, make) -> Path:
    """Make a capture with ``make(out)`` (its renderer's record), add the noise, record both."""
    suffix = "" if make is None else "-centres"
    cap_dir = args.work / f"{name}-d{depth}{suffix}"
    t = time.perf_counter()
    renderer = make(cap_dir) if make is not None else synthesize_capture(name, depth, cap_dir, args)
    noise = add_noise(cap_dir, args.noise, [SEED, depth, len(name)])
    results["captures"][cap_dir.name] = dict(renderer=renderer, noise=noise, seconds=time.perf_counter() - t)
    print(f"{cap_dir.name}: {renderer['spp']} spp, Mitsuba noise {renderer['noise']:.2%}, added std {noise['std']:.4g} "
          f"({time.perf_counter() - t:.0f} s)", flush=True)
    return cap_dir


def run(args) -> None:
    import jax

    from pbrfit.scene.capture import load_capture

    args.work = args.work or Path(tempfile.mkdtemp(prefix="pathtraced-"))
    args.work.mkdir(parents=True, exist_ok=True)
    results = dict(description=__doc__.splitlines()[0], size=args.size, views=args.views,
                   texture_size=args.texture_size, spp=args.spp, noise=args.noise, seed=SEED,
                   configs=dict(CONFIGS, **(EXTRAS if args.extras else {})), captures={}, fits=[],
                   devices=[str(d) for d in jax.devices()], machine=machine())
    relights = {}
    for name in args.scenes:
        for depth in args.depths:
            cap_dir = _capture(results, args, name, depth, None)
            if name not in relights:  # the relighting's scene and truth render: one per scene
                relights[name] = Relighting.prepare(load_capture(cap_dir), args.relight_views, args.relight_size,
                                                    args.relight_spp)
                results.setdefault("relight", {})[name] = relights[name].describe()
            for config, options in CONFIGS.items():
                _fit(results, args, name, depth, config, options, relights[name])
    if 4 in args.depths:
        picture(args.work, args.scenes, 4, args.out / "pathtraced.png")
    for config, options in (EXTRAS.items() if args.extras else ()):
        for name in args.scenes:
            _fit(results, args, name, max(args.depths), config, options, relights[name])
    print(f"wrote {args.out / 'pathtraced.json'} (work folder {args.work})")


def run_centres(args) -> None:
    """``--centres``: on an earlier run's work folder, the first scene's shallowest capture rendered
    at pixel centres (`centre_sampled_capture`), with the same noise, fitted per-pixel with occlusion."""
    from pbrfit.scene.capture import load_capture

    results = json.loads((args.out / "pathtraced.json").read_text())
    name, depth = args.scenes[0], min(args.depths)
    like = args.work / f"{name}-d{depth}"
    cap_dir = _capture(results, args, name, depth, lambda out: centre_sampled_capture(name, depth, like, out, args))
    relight = Relighting.prepare(load_capture(cap_dir), args.relight_views, args.relight_size, args.relight_spp)
    config = "per_pixel + occlusion"
    _fit(results, args, name, depth, config, CONFIGS[config], relight, capture="centres")


def _three(values: dict, fmt: str) -> str:
    return " / ".join(format(values[k], fmt) for k in ("base_color", "metallic", "roughness"))


def _line(row: dict) -> str:
    r = row["relight"]
    return (f"sure {_three({k: v['rmse'] for k, v in row['sure'].items()}, '.3f')}  all {_three(row['rmse'], '.3f')}  "
            f"2σ {_three(row['within_2sigma'], '.0%')}  relight {r['all']['raw_db']:.1f}/{r['all']['scaled_db']:.1f} dB "
            f"(diel {r['dielectric']['scaled_db']:.1f}, metal {r['metal']['scaled_db']:.1f})  {row['wall_s']:.0f} s")


def tables(results: dict) -> str:
    """The markdown tables of experiments/pathtraced.md, from pathtraced.json."""
    head = ("| scene | depth | fit | RMSE sure (texels) | RMSE all observed | within 2σ | relight raw / scaled dB "
            "| dielectric / metal dB (scaled) | wall s |\n|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for f in results["fits"]:
        sure = " / ".join(f"{f['sure'][k]['rmse']:.3f} ({f['sure'][k]['texels']})"
                          for k in ("base_color", "metallic", "roughness"))
        r = f["relight"]
        config = f["config"] + (", pixel-centre capture" if f.get("capture") == "centres" else "")
        chose = []
        choice = (f.get("ibl") or {}).get("choice")
        if choice is not None:  # a fit whose light model the fit chose (--ibl auto)
            occluded = " + occlusion" if (f.get("occlusion") or {}).get("used") else ""
            chose.append(f"light test: {f['ibl']['mode']}{occluded} kept")
        bounce = (f.get("occlusion") or {}).get("bounce") or {}
        if "residual_sigma" in bounce:  # a fit that chose whether blocked directions bring light
            chose.append(f"bounce test: {'kept' if bounce['used'] else 'not kept'}")
        if f.get("footprint") and "evidence" in f["footprint"]:  # a fit whose footprint the fit chose
            n = f["pixel_samples"]
            chose.append(f"footprint test: {f'{n} × {n} kept' if n > 1 else 'centres kept'}")
        if chose:
            config += f" ({'; '.join(chose)})"
        lines.append(f"| {f['scene']} | {f['max_depth']} | {config} | {sure} | {_three(f['rmse'], '.3f')} | "
                     f"{_three(f['within_2sigma'], '.0%')} | {r['all']['raw_db']:.1f} / {r['all']['scaled_db']:.1f} | "
                     f"{r['dielectric']['scaled_db']:.1f} / {r['metal']['scaled_db']:.1f} | {f['wall_s']:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["sphere-floor", "torus-floor"])
    ap.add_argument("--depths", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--texture-size", type=int, default=32)
    ap.add_argument("--spp", type=int, default=16384, help="Mitsuba samples per pixel of the captures")
    ap.add_argument("--noise", type=float, default=0.01, help="noise std as a fraction of the mean pixel over the mesh")
    ap.add_argument("--relight-views", type=int, default=4)
    ap.add_argument("--relight-size", type=int, default=64)
    ap.add_argument("--relight-spp", type=int, default=4096)
    ap.add_argument("--extras", action="store_true", help="also fit the deepest captures with EXTRAS")
    ap.add_argument("--centres", action="store_true", help="the pixel-centre probe (run_centres) on an earlier run's --work")
    ap.add_argument("--centre-spp", type=int, default=4096, help="--centres: Mitsuba samples per sub-pixel")
    ap.add_argument("--refit", nargs="+", choices=list(CONFIGS) + list(EXTRAS), metavar="CONFIG",
                    help="fit an earlier run's captures (--work) again with these CONFIGS (run_refit)")
    ap.add_argument("--tables", action="store_true", help="print the markdown tables from pathtraced.json and stop")
    ap.add_argument("--work", type=Path, help="where the captures and fits are kept (default: a new temporary folder)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args(argv)
    if args.tables:
        print(tables(json.loads((args.out / "pathtraced.json").read_text())))
    elif args.centres:
        if args.work is None:
            ap.error("--centres needs the --work folder of an earlier run")
        run_centres(args)
    elif args.refit:
        if args.work is None:
            ap.error("--refit needs the --work folder of an earlier run")
        run_refit(args)
    else:
        run(args)


if __name__ == "__main__":
    main()
