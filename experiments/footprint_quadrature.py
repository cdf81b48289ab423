"""The pixel footprint's quadrature: K x K supersampled linear captures fitted with n x n samples.

data_synth's ``plane-flash`` scene (a floor under a flash on each camera and two lamps: point
lights only, so the footprint is the one model difference) written as linear EXR images,
noiseless, supersampled K x K (K = 2: exactly what 2 x 2 samples average; K = 4: close to a
path tracer's box), fitted with ``pixel_samples`` 2, 3 and "auto" (which picks 3 x 3 for linear
images whose pixel-centre fit shows a box, `pbrfit.fitting.stages.footprint.AUTO_LINEAR_PIXEL_SAMPLES`).
Per fit: the all-observed RMSE of each map against the truth, the footprint kept and the wall time.

    python experiments/footprint_quadrature.py [--size 64] [--views 8] [--texture-size 32] [--work DIR]

Writes experiments/results/footprint_quadrature.json; docs/footprint.md quotes the table.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

SUPERSAMPLES = (2, 4)
FITTED = (2, 3, "auto")


def main(argv=None) -> None:
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit import fit
    from pbrfit.fitting.result import map_rmse
    from pbrfit.io.material_files import read_material
    from pbrfit.scene.capture import load_capture

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--texture-size", type=int, default=32)
    ap.add_argument("--work", type=Path)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="footprint-"))
    rows = []
    for k in SUPERSAMPLES:
        cap = work / f"plane-flash-ss{k}"
        if not cap.exists():
            synthesize(make_scene("plane-flash", seed=1, size=args.size, views=args.views,
                                  texture_size=args.texture_size, noise=0.0, image_format="exr", supersample=k),
                       cap, write_contact_sheet=False)
        capture, truth = load_capture(cap), read_material(cap / "truth")
        for n in FITTED:
            t = time.perf_counter()
            res = fit(capture, resolution=args.texture_size, pixel_samples=n)
            seconds = time.perf_counter() - t
            rmse = map_rmse(truth, res)  # over the observed texels
            rows.append(dict(supersample=k, pixel_samples=n, kept=res.report.get("pixel_samples", 1),
                             seconds=seconds, rmse=rmse))
            print(f"supersampled {k}x{k}, fitted {n}: kept {rows[-1]['kept']}, RMSE "
                  + " / ".join(f"{v:.2g}" for v in rmse.values()) + f", {seconds:.0f} s", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "footprint_quadrature.json").write_text(json.dumps(dict(
        description=__doc__.splitlines()[0], scene="plane-flash", size=args.size, views=args.views,
        texture_size=args.texture_size, rows=rows), indent=1))


if __name__ == "__main__":
    main()
