"""`pbrfit demo`: synthesize a capture on the embedded defaults, fit it, print what came back.

The scene is data_synth's ``demo`` preset: a textured sphere on a textured floor under a
procedural sky and a sun-like point light, a few noisy views. Nothing is downloaded. The
capture goes to ``OUT/capture`` and the fit to ``OUT/fit``.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np

from data_synth.presets import make_scene
from data_synth.writer import synthesize

from .fit import run_fit
from ..errors import CaptureError, listed
from ..fitting.options import FitOptions
from ..fitting.parameters import FIT_GROUPS
from ..fitting.runner import compile_summary
from ..io.atomic import check_output_dir
from ..io.material_files import read_material
from ..fitting.result import truth_at
from ..render.views import default_cache_dir
from ..scene.capture import load_capture

__all__ = ["run", "run_demo", "recovery_table", "CONFIDENT_SIGMA", "DEMO_FOLDERS"]


#: The demo's "confident" texels: those whose reported standard error is at most this.
CONFIDENT_SIGMA = 0.05
_MAPS = ("base_color", "metallic", "roughness")


def recovery_table(fitted, truth, sigma, coverage) -> list[dict]:
    """Per map, over observed texels: RMSE against the truth; the RMSE and count of the texels
    whose standard error is at most `CONFIDENT_SIGMA`; the median σ; and the fraction of texel
    channels whose error is within 2σ (≈ 95% when the uncertainty is honest)."""
    x = np.concatenate([np.asarray(fitted.base_color), np.asarray(fitted.metallic), np.asarray(fitted.roughness)], -1)
    truth = truth_at(truth, fitted.resolution)  # resampled as `pbrfit.fitting.result.map_rmse` does
    t = np.concatenate([np.asarray(truth.base_color), np.asarray(truth.metallic), np.asarray(truth.roughness)], -1)
    sig = np.asarray(sigma)
    seen = np.asarray(coverage) > 0
    rows = []
    for name in _MAPS:
        ch = list(FIT_GROUPS[name])
        err, s = (x - t)[seen][:, ch], sig[seen][:, ch]
        sure = np.max(s, axis=1) <= CONFIDENT_SIGMA
        rows.append(dict(
            map=name, rmse=float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
            confident=int(sure.sum()), rmse_confident=float(np.sqrt(np.mean(err[sure] ** 2))) if sure.any() else float("nan"),
            median_sigma=float(np.median(s)) if s.size else float("nan"),
            within_2sigma=float(np.mean(np.abs(err) <= 2 * s)) if s.size else float("nan"),
        ))
    return rows


def _table(rows: list[dict], observed: int) -> str:
    """The recovery table: first the texels the fit is sure of (σ at most `CONFIDENT_SIGMA`), how
    many they are and their RMSE, then the RMSE over every observed texel, the median σ and the
    calibration column."""
    sure = f"σ ≤ {CONFIDENT_SIGMA:g}"
    head = f"{'map':<12}{'sure texels':>12}{'RMSE, ' + sure:>16}{'RMSE, all':>11}{'median σ':>10}{'|err| ≤ 2σ':>12}"
    lines = [head]
    for r in rows:
        sure_rmse = f"{r['rmse_confident']:.4f}" if r["confident"] else "-"  # no texel to measure
        lines.append(f"{r['map']:<12}{r['confident']:>12}{sure_rmse:>16}{r['rmse']:>11.4f}"
                     f"{r['median_sigma']:>10.4f}{r['within_2sigma']:>11.0%}")
    lines.append(f"sure texels: observed, with {sure}; RMSE, all: over all {observed} observed texels, "
                 "the unsure ones included.")
    return "\n".join(lines)


#: What the demo writes in its --out folder: the synthesized capture and the fit's output.
DEMO_FOLDERS = ("capture", "fit")
#: ... and what a demo killed while writing them leaves (`pbrfit.io.atomic.atomic_dir`'s folders
#: beside them), which the next demo may find.
_LEFTOVER = re.compile(r"\.(?:capture|fit)\..+\.(?:tmp|old)")


def run(args) -> int:
    """`pbrfit demo` on its parsed arguments; returns the exit status."""
    return run_demo(out=args.out, quiet=args.quiet)


def run_demo(out: str = "pbrfit-demo", quiet: bool = False, seed: int = 0, **scene) -> int:
    """Synthesize, fit and report; returns the exit status. `scene` overrides the preset's
    parameters (``size``, ``views``, ``texture_size``...; see `data_synth.presets.make_scene`)."""
    def say(message: str) -> None:
        if not quiet:
            print(message, flush=True)

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CaptureError(f"{out}: exists and is not a folder; choose another --out")
    if out.is_dir():  # as fit and render refuse a folder they did not write: the demo's holds its two
        other = sorted(p.name for p in out.iterdir() if p.name not in DEMO_FOLDERS and not _LEFTOVER.fullmatch(p.name))
        if other:
            raise CaptureError(f"{out}: holds what the demo did not write ({listed(other)}); choose another --out")
    check_output_dir(out / "capture", "capture")
    check_output_dir(out / "fit", "fit")
    start = time.perf_counter()
    scene = make_scene("demo", seed=seed, **scene)
    say(f"pbrfit demo: synthesizing '{scene.name}' ({scene.num_views} views of {scene.width}x{scene.height}) ...")
    synthesize(scene, out / "capture")
    t_synth = time.perf_counter() - start
    capture = load_capture(out / "capture")
    say(f"  capture written to {out / 'capture'} in {t_synth:.1f} s; fitting ...")
    result, _ = run_fit(capture, out / "fit", FitOptions(), default_cache_dir(), quiet)
    seen = np.asarray(result.coverage) > 0
    truth = read_material(capture.truth_dir)
    r = result.report
    h, w = r["resolution"]
    say("")
    say(_table(recovery_table(result.material, truth, result.uncertainty, result.coverage), int(seen.sum())))
    say("")
    say(
        f"{h}x{w} maps, {r['steps']} solver steps, fit {r['wall_time']:.1f} s "
        f"({compile_summary(r['times'])}), total {time.perf_counter() - start:.1f} s; "
        f"{int(seen.sum())} of {seen.size} texels observed"
    )
    say(f"wrote {out / 'fit'} (maps, uncertainty.exr, material.glb, report.json; pictures: maps.png, views/)")
    return 0
