"""Fits under environment light rendered as a path tracer would: split sum against per-pixel integrals.

A capture made by another renderer integrates the environment exactly; pbrfit's default fit
models it with the split sum (`pbrfit.lighting.ibl`), whose error under a sun is tens of percent
(`experiments/ibl_accuracy.py`). Here data_synth scenes are rendered with their environment
light by the Monte Carlo reference (``Model(ibl="monte_carlo")``, `Scene.mc_samples` steps per
pixel), and each is fitted with ``ibl="split_sum"`` and ``ibl="per_pixel"`` (`pbrfit.lighting.pixel_ibl`),
both from pbrfit's default start and, as a reference, from the true maps ("oracle": structured LM
started at the truth, the minimum nearest the truth that each model's objective has). The gap
between the two oracles is the bias the split sum puts into fits; the default rows are what a
user gets. Per row: per-map RMSE over observed and over well-observed texels (`solvers.py`), the
final objective (and for the oracles, each model's objective at the true maps: how far the model
is from the images where it should fit them), and the wall time split into the per-pixel
precomputation and the rest.

    python experiments/env_fits.py [--scenes demo sphere-env] [--mc-samples 4096] [--pixel-samples 128 512]

Writes experiments/results/env_fits.json. The recorded run took 2 min 46 s on one H100; on a 2-core
CPU the per-pixel integrals alone would take about 6 minutes (0.6 and 2.5 ms per pixel at 128 and
512 samples; the oracles read the fits' tables from the cache), and the Monte Carlo renders at
4,096 samples about two hours (sphere-env at 16 samples: 26 s).
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
from solvers import _metrics, _oracle, machine  # noqa: E402

SCENES = ("demo", "sphere-env")


def _objective_at(obs, model, tables, truth) -> float:
    """1/2 Σ (image value of the true maps, bilinear at each pixel's uv - the image value)²."""
    from pbrfit.physics.color import encode
    from pbrfit.physics.material import material_at
    from pbrfit.render.shade import shade

    s = material_at(truth, obs.uv, "repeat")
    rad = shade(obs.normal, obs.view, obs.light_l, obs.light_radiance, s.base_color, s.metallic, s.roughness, model,
                tables)
    value = np.asarray(encode(rad, obs.exposure[:, None], obs.tonemap, obs.color_space))
    return float(0.5 * np.sum((value - np.asarray(obs.target)) ** 2))


def run(scenes, mc_samples: int, pixel_samples, out: Path):
    import jax

    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fitting.api import fit
    from pbrfit.io.material_files import read_material
    from pbrfit.fitting.observations import observations_from_capture
    from pbrfit.lighting.pixel_ibl import PixelIBLSettings, pixel_ibl
    from pbrfit.scene.capture import load_capture
    from pbrfit.render.views import capture_environment, capture_ibl, model_for_capture

    rows = []
    for name in scenes:
        with tempfile.TemporaryDirectory() as tmp:
            scene = make_scene(name, 0)
            scene = scene.replace(model=scene.model.replace(ibl="monte_carlo"), mc_samples=mc_samples)
            t = time.perf_counter()
            synthesize(scene, Path(tmp) / "cap")
            synth_s = time.perf_counter() - t
            print(f"{name}: rendered with the Monte Carlo reference ({mc_samples} samples) in {synth_s:.0f} s", flush=True)
            capture = load_capture(Path(tmp) / "cap")
            truth = read_material(Path(tmp) / "cap" / "truth")
            resolution = tuple(truth.resolution)
            cache = Path(tmp) / "cache"
            configs = [("split_sum", None)] + [("per_pixel", PixelIBLSettings(samples=k)) for k in pixel_samples]
            for mode, settings in configs:
                label = mode if settings is None else f"{mode} ({settings.samples} samples)"
                result = fit(capture, ibl=mode, pixel_ibl_settings=settings or PixelIBLSettings(),
                             resolution=resolution, cache_dir=cache, background_compile=False)
                m = _metrics(truth, result.material, result.coverage, result.uncertainty)
                times = result.report["times"]
                row = dict(scene=name, ibl=mode, samples=None if settings is None else settings.samples,
                           start="default", **m, final_loss=result.report["final_loss"],
                           ibl_s=result.report["ibl"]["seconds"], wall_s=result.report["wall_time"],
                           compile_s=times.get("compile", 0.0), steps=result.report["steps"])
                rows.append(row)
                print(f"  {label:24s} default  rmse {_fmt(m['rmse'])}  well {_fmt(m['rmse_well'])}  "
                      f"loss {row['final_loss']:.4g}  ibl {row['ibl_s']:.1f} s  wall {row['wall_s']:.1f} s", flush=True)
            # oracles: the same observations and tables, LM from the truth; and each model's objective at the truth
            obs = observations_from_capture(capture, cache_dir=cache)
            base = model_for_capture(capture, truth)
            for mode, settings in configs:
                label = mode if settings is None else f"{mode} ({settings.samples} samples)"
                model = base.replace(ibl=mode, metallic=True)
                tables = (capture_ibl(capture, model=model) if mode == "split_sum" else
                          pixel_ibl(capture_environment(capture), np.asarray(obs.normal), np.asarray(obs.view), model,
                                    settings, cache_dir=cache))  # the fit's own tables, from the cache
                material, coverage, times, steps, loss = _oracle(obs, model, tables, truth, resolution)
                m = _metrics(truth, material, coverage)
                at_truth = _objective_at(obs, model, tables, truth)
                rows.append(dict(scene=name, ibl=mode, samples=None if settings is None else settings.samples,
                                 start="truth", **m, steps=steps, solve_s=times["solve"], final_loss=loss,
                                 objective_at_truth=at_truth))
                print(f"  {label:24s} oracle   rmse {_fmt(m['rmse'])}  well {_fmt(m['rmse_well'])}  "
                      f"objective at the truth {at_truth:.4g}", flush=True)
    results = dict(description=__doc__.splitlines()[0], mc_samples=mc_samples, rows=rows,
                   levels=PixelIBLSettings().levels, devices=[str(d) for d in jax.devices()],
                   machine=machine())
    out.mkdir(parents=True, exist_ok=True)
    (out / "env_fits.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {out / 'env_fits.json'}")


def _fmt(r: dict) -> str:
    return " / ".join(f"{r[k]:.3f}" for k in ("base_color", "metallic", "roughness"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--mc-samples", type=int, default=4096, help="Monte Carlo steps per pixel of the rendered images")
    ap.add_argument("--pixel-samples", type=int, nargs="+", default=[128, 512],
                    help="per-pixel integral sample counts to fit with")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args(argv)
    run(args.scenes, args.mc_samples, args.pixel_samples, args.out)


if __name__ == "__main__":
    main()
