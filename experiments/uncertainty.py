"""Calibration of the reported uncertainty: repeated fits of one scene under fresh noise.

`pbrfit.fit` reports each texel's standard error from the Gauss-Newton normal matrix
(`pbrfit.fitting.uncertainty`): with ``uncertainty_radius`` 0 from the texel's own block (its neighbours
held), with r > 0 from the (2 r + 1)² texels around it (a Schur complement of that window's
matrix). This script measures which is honest. It renders the peer scene (`peer-plane`, seed 0,
noiseless, linear EXR) once, then adds N fresh draws of 1% noise to its images, in memory
(``gaussian``: σ = 0.01 of a value of 1; ``relative``: 1% of each pixel's value), and fits each
draw as ``pbrfit fit CAPTURE --resolution 64`` does, once per radius. The maps do not depend on
the radius (checked); only the reported σ does. Per noise model and radius, over the observed
texels of all draws, for base colour (R, G, B together) and roughness:

- ``within_2sigma``: the share of texels whose error is within the reported 2σ (a Gaussian: 95%);
- ``median_z``: the median of |error| / σ (a Gaussian: 0.674);
- ``spread``: the median over texels of the N fits' standard deviation over the root mean
  square of their reported σ (honest: 1; below 1, σ is conservative).

Metallic is left out: its truth is 0, on the bound, where errors are one-sided.

Each draw is fitted once per ``--noise-levels`` entry as well: ``uniform`` (plain least squares,
the default of `pbrfit.fit`) and ``estimated`` (`pbrfit.fitting.noise`: a second fit weighted by the
noise level function of the first's residuals). ``--noise-models`` adds ``poisson_gaussian``
(shot noise of std 0.01 at a value of 1 plus read noise of 0.0025, `data_synth.noise`).

    python experiments/uncertainty.py [--draws 8] [--radii 0 1 2] [--noise-models gaussian relative]
        [--noise-levels uniform]

Writes experiments/results/uncertainty.json (a run replaces the rows it measures and keeps the
others; each row names the commit it was measured at) and prints the table of
experiments/uncertainty.md. About 10 minutes on a 2-core CPU with the defaults.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

NOISE_MODELS = ("gaussian", "relative")
NOISE_LEVELS = ("uniform",)
SIGMA = 0.01
#: name: channels of the (H, W, 5) maps and uncertainty
CHANNELS = {"base_color": [0, 1, 2], "roughness": [4]}


def _stack(material) -> np.ndarray:
    return np.concatenate([np.asarray(material.base_color), np.asarray(material.metallic),
                           np.asarray(material.roughness)], axis=-1)


def run(draws: int, radii, noise_models=NOISE_MODELS, noise_levels=NOISE_LEVELS) -> list[dict]:
    from data_synth.noise import add_noise
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fitting.api import fit
    from pbrfit.io.material_files import read_material
    from pbrfit.scene.capture import load_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cap_dir = Path(tmp) / "peer-plane"
        synthesize(make_scene("peer-plane", seed=0), cap_dir)
        clean = load_capture(cap_dir)
        truth = _stack(read_material(cap_dir / "truth"))
        runs = [(level, r) for level in noise_levels for r in radii]
        for model in noise_models:
            fits = {run: [] for run in runs}
            for draw in range(draws):
                rng = np.random.default_rng([draw, 0x0CA1])
                frames = [dataclasses.replace(f, image=add_noise(f.image, SIGMA, rng, model)) for f in clean.frames]
                capture = dataclasses.replace(clean, frames=frames)
                maps = {}
                for level, r in runs:
                    t0 = time.perf_counter()
                    res = fit(capture, resolution=64, uncertainty_radius=r, noise_level=level,
                              cache_dir=Path(tmp) / "cache")
                    wall = time.perf_counter() - t0
                    x = _stack(res.material)
                    if level not in maps:
                        maps[level] = x
                    elif not np.array_equal(x, maps[level]):
                        raise RuntimeError(f"{model} draw {draw}: the maps differ between radii")
                    fits[level, r].append(dict(x=x, sigma=np.asarray(res.uncertainty), seen=res.coverage > 0,
                                               wall=wall, post=res.report["times"]["post"]))
                print(f"{model} draw {draw}: " + ", ".join(
                    f"{level} r={r} {fits[level, r][-1]['wall']:.1f} s" for level, r in runs), flush=True)
            for level, r in runs:
                f = fits[level, r]
                rows.append(dict(noise=model, noise_level=level, radius=r, draws=draws, commit=_commit(),
                                 **_scores(f, truth), post_s=float(np.median([x["post"] for x in f])),
                                 wall_s=float(np.median([x["wall"] for x in f]))))
    return rows


def _commit() -> str:
    """The repository's commit (with "+" when the working tree differs from it), or "unknown"."""
    import subprocess

    here = Path(__file__).parent
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+" if dirty else "")


def _key(row: dict) -> tuple:
    return row["noise"], row.get("noise_level", "uniform"), row["radius"]


def merge(old: list[dict], new: list[dict]) -> list[dict]:
    """The rows of `old` that `new` does not measure again, then `new`'s, ordered by noise model,
    noise level and radius."""
    fresh = {_key(r) for r in new}
    rows = [r for r in old if _key(r) not in fresh] + list(new)
    order = {m: i for i, m in enumerate(("gaussian", "relative", "poisson_gaussian"))}
    return sorted(rows, key=lambda r: (order.get(r["noise"], 9), r.get("noise_level", "uniform") != "uniform",
                                       r["radius"]))


def _scores(fits: list[dict], truth: np.ndarray) -> dict:
    seen = np.all([f["seen"] for f in fits], axis=0)
    x = np.stack([f["x"][seen] for f in fits])  # (N, texels, 5)
    sigma = np.stack([f["sigma"][seen] for f in fits])
    err = x - truth[seen][None]
    out = {}
    for name, cs in CHANNELS.items():
        e, s = err[..., cs], sigma[..., cs]
        spread = np.std(x[..., cs], axis=0, ddof=1) / np.sqrt(np.mean(s ** 2, axis=0))
        out[name] = dict(within_2sigma=float(np.mean(np.abs(e) <= 2 * s)), median_z=float(np.median(np.abs(e) / s)),
                         spread=float(np.median(spread)), rmse=float(np.sqrt(np.mean(e ** 2))))
    return out


def table(rows: list[dict]) -> str:
    out = ["| noise | noise level | radius | within 2σ (%): base / roughness | median \\|error\\| / σ | spread / σ "
           "| RMSE: base / roughness | median post s | median wall s | at |",
           "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in rows:
        b, g = r["base_color"], r["roughness"]
        out.append(f"| {r['noise']} | {r.get('noise_level', 'uniform')} | {r['radius']} "
                   f"| {100 * b['within_2sigma']:.1f} / {100 * g['within_2sigma']:.1f} "
                   f"| {b['median_z']:.3f} / {g['median_z']:.3f} | {b['spread']:.3f} / {g['spread']:.3f} "
                   f"| {b['rmse']:.4f} / {g['rmse']:.4f} | {r['post_s']:.2f} | {r['wall_s']:.1f} "
                   f"| {r.get('commit', '666df53')} |")
    out.append("")
    out.append("A Gaussian error with an honest σ: 95.4% within 2σ, median |error| / σ 0.674, spread / σ 1.")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--radii", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--noise-models", nargs="+", default=list(NOISE_MODELS),
                        choices=["gaussian", "relative", "poisson_gaussian"])
    parser.add_argument("--noise-levels", nargs="+", default=list(NOISE_LEVELS), choices=["uniform", "estimated"])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    parser.add_argument("--table", action="store_true", help="print uncertainty.md's table from uncertainty.json")
    args = parser.parse_args()
    path = Path(args.out) / "uncertainty.json"
    if args.table:
        print(table(json.loads(path.read_text())["rows"]))
        return
    from solvers import write_rows  # experiments/solvers.py: the rows with the host and package versions

    rows = run(args.draws, args.radii, args.noise_models, args.noise_levels)
    if path.is_file():
        rows = merge(json.loads(path.read_text())["rows"], rows)
    write_rows(path, rows)
    print(table(rows))


if __name__ == "__main__":
    main()
