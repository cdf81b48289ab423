"""Calibration of the reported uncertainty: repeated fits of one scene under fresh noise.

`pbrfit.fit` reports each texel's standard error from the Gauss-Newton normal matrix
(`pbrfit.uncertainty`): with ``uncertainty_radius`` 0 from the texel's own block (its neighbours
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

    python experiments/uncertainty.py [--draws 8] [--radii 0 1 2]

Writes experiments/results/uncertainty.json and prints the table of experiments/uncertainty.md.
About 10 minutes on a 2-core CPU.
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
SIGMA = 0.01
#: name: channels of the (H, W, 5) maps and uncertainty
CHANNELS = {"base_color": [0, 1, 2], "roughness": [4]}


def _stack(material) -> np.ndarray:
    return np.concatenate([np.asarray(material.base_color), np.asarray(material.metallic),
                           np.asarray(material.roughness)], axis=-1)


def run(draws: int, radii) -> list[dict]:
    from data_synth.noise import add_noise
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fit import fit
    from pbrfit.io import read_material
    from pbrfit.scene import load_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cap_dir = Path(tmp) / "peer-plane"
        synthesize(make_scene("peer-plane", seed=0), cap_dir)
        clean = load_capture(cap_dir)
        truth = _stack(read_material(cap_dir / "truth"))
        for model in NOISE_MODELS:
            fits = {r: [] for r in radii}
            for draw in range(draws):
                rng = np.random.default_rng([draw, 0x0CA1])
                frames = [dataclasses.replace(f, image=add_noise(f.image, SIGMA, rng, model)) for f in clean.frames]
                capture = dataclasses.replace(clean, frames=frames)
                maps = None
                for r in radii:
                    t0 = time.perf_counter()
                    res = fit(capture, resolution=64, uncertainty_radius=r, cache_dir=Path(tmp) / "cache")
                    wall = time.perf_counter() - t0
                    x = _stack(res.material)
                    if maps is None:
                        maps = x
                    elif not np.array_equal(x, maps):
                        raise RuntimeError(f"{model} draw {draw}: the maps differ between radii")
                    fits[r].append(dict(x=x, sigma=np.asarray(res.uncertainty), seen=res.coverage > 0, wall=wall,
                                        post=res.report["times"]["post"]))
                print(f"{model} draw {draw}: " + ", ".join(f"r={r} {fits[r][-1]['wall']:.1f} s" for r in radii),
                      flush=True)
            for r in radii:
                rows.append(dict(noise=model, radius=r, draws=draws, **_scores(fits[r], truth),
                                 post_s=float(np.median([f["post"] for f in fits[r]])),
                                 wall_s=float(np.median([f["wall"] for f in fits[r]]))))
    return rows


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
    out = ["| noise | radius | within 2σ (%): base / roughness | median \\|error\\| / σ | spread / σ "
           "| median post s |",
           "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        b, g = r["base_color"], r["roughness"]
        out.append(f"| {r['noise']} | {r['radius']} | {100 * b['within_2sigma']:.1f} / {100 * g['within_2sigma']:.1f} "
                   f"| {b['median_z']:.3f} / {g['median_z']:.3f} | {b['spread']:.3f} / {g['spread']:.3f} "
                   f"| {r['post_s']:.2f} |")
    out.append("")
    out.append("A Gaussian error with an honest σ: 95.4% within 2σ, median |error| / σ 0.674, spread / σ 1.")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--radii", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    parser.add_argument("--table", action="store_true", help="print uncertainty.md's table from uncertainty.json")
    args = parser.parse_args()
    path = Path(args.out) / "uncertainty.json"
    if args.table:
        print(table(json.loads(path.read_text())["rows"]))
        return
    from solvers import machine  # experiments/solvers.py: the host and package versions

    rows = run(args.draws, args.radii)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(dict(machine=machine(), rows=rows), indent=1))
    tmp.replace(path)
    print(table(rows))


if __name__ == "__main__":
    main()
