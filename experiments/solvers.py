"""Solver and strategy comparison: per-map RMSE against wall time on data_synth captures.

Every configuration fits the same capture (ray casting done once per scene and shared), and
records per-map RMSE over observed texels, steps, and the wall time split into compile and
solve. Results go to experiments/results/solvers.json and a plot to solvers.png.

    python experiments/solvers.py [--scenes peer-plane plane-flash] [--quick]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

CONFIGS = {
    # name: fit_observations keyword arguments
    "structured (grid init)": dict(solver="structured", init="grid"),
    "structured (prior init)": dict(solver="structured", init="prior"),
    "structured (coarse-to-fine)": dict(solver="structured", init="prior", coarse_to_fine=True),
    "structured (grid + coarse-to-fine)": dict(solver="structured", init="grid", coarse_to_fine=True),
    "lm (optimistix)": dict(solver="lm", init="grid", max_steps=20),
    "gn (optimistix)": dict(solver="gn", init="grid", max_steps=20),
    "dogleg (optimistix)": dict(solver="dogleg", init="grid", max_steps=20),
    "lbfgs (optimistix)": dict(solver="lbfgs", init="grid", max_steps=200),
    "ncg (optimistix)": dict(solver="ncg", init="grid", max_steps=200),
    "adam (optimistix)": dict(solver="adam", init="grid", max_steps=300),
}
SCENES = {"peer-plane": {}, "plane-flash": {}, "sphere-env": {}, "spheres-grid": {}}


def run(scenes, configs, out_dir: Path):
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fit import fit_observations, map_rmse, model_for_capture, _ibl_for_capture
    from pbrfit.io import read_material
    from pbrfit.observations import observations_from_capture
    from pbrfit.scene import load_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            cap_dir = Path(tmp) / scene
            synthesize(make_scene(scene, seed=0, **SCENES[scene]), cap_dir)
            t0 = time.perf_counter()
            capture = load_capture(cap_dir)
            model = model_for_capture(capture)
            ibl = _ibl_for_capture(capture, model)
            obs = observations_from_capture(capture)
            setup = time.perf_counter() - t0
            truth = read_material(cap_dir / "truth")
            resolution = truth.resolution
            for name in configs:
                kwargs = dict(CONFIGS[name])
                t1 = time.perf_counter()
                try:
                    res = fit_observations(obs, model=model, ibl=ibl, resolution=resolution, **kwargs)
                except Exception as exc:  # a solver that fails is a result too
                    rows.append(dict(scene=scene, config=name, error=f"{type(exc).__name__}: {exc}"[:300]))
                    print(scene, name, "failed:", rows[-1]["error"], flush=True)
                    continue
                wall = time.perf_counter() - t1
                rmse = map_rmse(truth, res)
                rows.append(dict(scene=scene, config=name, rmse=rmse, wall=wall, setup=setup,
                                 times=res.report["times"], steps=res.report["steps"], levels=res.report["levels"],
                                 final_loss=res.report["final_loss"]))
                print(scene, name, {k: round(v, 4) for k, v in rmse.items()}, f"{wall:.1f}s",
                      {k: round(v, 1) for k, v in res.report["times"].items()}, flush=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "solvers.json").write_text(json.dumps(rows, indent=1))
    plot(rows, out_dir / "solvers.png")
    return rows


def plot(rows, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "rmse" in r]
    scenes = sorted({r["scene"] for r in ok})
    fig, axes = plt.subplots(1, max(len(scenes), 1), figsize=(6 * max(len(scenes), 1), 4.5), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for r in (r for r in ok if r["scene"] == scene):
            total = r["rmse"]["base_color"] + r["rmse"]["roughness"] + r["rmse"]["metallic"]
            ax.scatter(r["wall"], total, s=30)
            ax.annotate(r["config"], (r["wall"], total), fontsize=7)
        ax.set_xlabel("fit wall time (s, compile included; 2-core CPU)")
        ax.set_ylabel("RMSE base + roughness + metallic")
        ax.set_yscale("log")
        ax.set_title(scene)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["peer-plane", "plane-flash"])
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS))
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    args = parser.parse_args()
    run(args.scenes, args.configs, Path(args.out))
