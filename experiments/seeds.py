"""Seed study: the acceptance scenes rendered with other truth maps, fitted with and without the repair.

Every number in solvers.md is seed 0's. Captures we have not seen are made with other truth maps,
so this script renders the peer scene (`peer-plane`: noiseless, with 1% noise, and with noise of
1% of each pixel's value) at seeds 0 to N-1 and the flash scene (`plane-flash`, 1% noise of
either kind) at seeds 0 to 2, and fits each as ``pbrfit fit CAPTURE`` does (`pbrfit.fit`, the
default configuration; ``--resolution 64`` on the peer scene), once with the repair
(`pbrfit.fitting.stages.repair`, the default) and once without. Each row
records the per-map RMSE against the truth over observed texels, the share of texel channels
within the reported 2σ, the steps, the wall time of the whole `fit` call (G-buffers cached from
the first of the two, compiles shared within the process) and the repair's passes.

    python experiments/seeds.py [--seeds 10] [--scenes peer-plane ...] [--merge]

Writes experiments/results/seeds.json and prints the tables of experiments/seeds.md. About 25
minutes on a 2-core CPU for all the scenes.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

#: name: (data_synth preset, make_scene overrides, the acceptance targets base / metallic / roughness,
#: the fit's --resolution (None: the default), the most seeds it runs)
SCENES = {
    "peer-plane": ("peer-plane", {}, (0.005, 0.01, 0.02), 64, None),
    "peer-plane-noisy": ("peer-plane", dict(noise=0.01), (0.01, 0.02, 0.03), 64, None),
    "peer-plane-noisy-relative": ("peer-plane", dict(noise=0.01, noise_model="relative"), (0.01, 0.02, 0.03), 64,
                                  None),
    "plane-flash": ("plane-flash", {}, (0.04, 0.05, 0.04), None, 3),
    "plane-flash-relative": ("plane-flash", dict(noise_model="relative"), (0.04, 0.05, 0.04), None, 3),
}
MAPS = ("base_color", "metallic", "roughness")


def run(scenes, seeds: int) -> list[dict]:
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.cli.demo import recovery_table
    from pbrfit.fitting.api import fit
    from pbrfit.io.material_files import read_material
    from pbrfit.scene.capture import load_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            preset, overrides, _, resolution, most = SCENES[scene]
            for seed in range(min(seeds, most or seeds)):
                cap_dir = Path(tmp) / f"{scene}-{seed}"
                synthesize(make_scene(preset, seed=seed, **overrides), cap_dir)
                capture = load_capture(cap_dir)
                truth = read_material(cap_dir / "truth")
                for repair in (True, False):
                    t0 = time.perf_counter()
                    res = fit(capture, resolution=resolution, repair=repair, cache_dir=Path(tmp) / "cache")
                    wall = time.perf_counter() - t0
                    table = {r["map"]: r for r in recovery_table(res.material, truth, res.uncertainty, res.coverage)}
                    row = dict(scene=scene, seed=seed, repair=repair, wall=wall, steps=res.report["steps"],
                               final_loss=res.report["final_loss"],
                               rmse={m: table[m]["rmse"] for m in MAPS},
                               within_2sigma={m: table[m]["within_2sigma"] for m in MAPS},
                               passes=(res.report.get("repair") or {}).get("passes", []))
                    rows.append(row)
                    print(f"{scene} seed {seed} {'repair' if repair else 'no repair':9} | "
                          + " ".join(f"{m} {row['rmse'][m]:.4f}" for m in MAPS)
                          + f" | {row['steps']} steps, {wall:.1f} s | passes {row['passes']}", flush=True)
    return rows


def table(rows: list[dict]) -> str:
    """Markdown: per scene, one line per seed with both fits' RMSE, and a summary of the misses."""
    out = []
    for scene, (_, _, target, _, _) in SCENES.items():
        mine = [r for r in rows if r["scene"] == scene]
        if not mine:
            continue
        out += [f"### {scene} (targets base / metallic / roughness ≤ {' / '.join(f'{t:g}' for t in target)})", "",
                "| seed | with the repair | without | within 2σ (%, with) "
                "| repair passes (kind flagged → texels kept) | wall s (with / without) |",
                "| ---: | ---: | ---: | ---: | --- | ---: |"]
        fmt = lambda r: " / ".join(f"{r['rmse'][m]:.4f}" + ("*" if r["rmse"][m] > t else "")
                                   for m, t in zip(MAPS, target))
        kept = lambda p: p.get("texels_kept", 0) if p.get("kept") else 0
        for seed in sorted({r["seed"] for r in mine}):
            w = next(r for r in mine if r["seed"] == seed and r["repair"])
            wo = next(r for r in mine if r["seed"] == seed and not r["repair"])
            passes = ", ".join(f"{p.get('kind', 'misfit')} {p['flagged']} → {kept(p)}"
                               for p in w["passes"] if p["flagged"]) or "none flagged"
            within = " / ".join(f"{100 * w['within_2sigma'][m]:.0f}" for m in MAPS)
            out.append(f"| {seed} | {fmt(w)} | {fmt(wo)} | {within} | {passes} | {w['wall']:.1f} / {wo['wall']:.1f} |")
        for repair in (True, False):
            sel = [r for r in mine if r["repair"] == repair]
            worst = {m: max(r["rmse"][m] for r in sel) for m in MAPS}
            misses = sum(any(r["rmse"][m] > t for m, t in zip(MAPS, target)) for r in sel)
            out.append("")
            out.append(f"{'With' if repair else 'Without'} the repair: {misses} of {len(sel)} seeds miss a target; "
                       f"worst " + " / ".join(f"{worst[m]:.4f}" for m in MAPS)
                       + f"; median wall {np.median([r['wall'] for r in sel]):.1f} s.")
        out.append("")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    parser.add_argument("--tables", action="store_true", help="print seeds.md's tables from seeds.json")
    parser.add_argument("--merge", action="store_true", help="keep the other scenes' rows already in seeds.json")
    args = parser.parse_args()
    path = Path(args.out) / "seeds.json"
    if args.tables:
        print(table(json.loads(path.read_text())["rows"]))
        return
    from solvers import write_rows  # experiments/solvers.py: the rows with the host and package versions

    rows = run(args.scenes, args.seeds)
    if args.merge and path.exists():
        rows = [r for r in json.loads(path.read_text())["rows"] if r["scene"] not in args.scenes] + rows
        rows.sort(key=lambda r: list(SCENES).index(r["scene"]))
    write_rows(path, rows)
    print(table(rows))


if __name__ == "__main__":
    main()
