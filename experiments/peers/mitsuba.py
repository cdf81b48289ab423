"""The Mitsuba 3 peer anchor: pbrfit's peer-scene fit and Mitsuba 3's, one after the other on one machine.

1. pbrfit: ``pbrfit synth peer-plane --noise 0`` then ``pbrfit fit CAP --resolution 64 --cache
   EMPTY`` in a new process (cold caches), launch to exit; base colour and roughness RMSE from
   its ``report.json`` (``truth_rmse``, over observed texels).
2. Mitsuba: ``mitsuba_peer_fit.py`` (beside this file, the reference run copied unchanged: a
   ``rectangle`` with a ``principled`` BSDF, 6 views of 128², 4 point lights, 64² maps, metallic
   0, Adam on ``prb`` renders at 8 spp) in a new process, launch to exit; base colour and
   roughness RMSE over the texels some view sees, from its last checkpoint.

The two do not fit the same images. The peer script renders its own targets with Mitsuba's
path tracer; pbrfit fits its own synth of the layout: the same counts and sizes (a 2 × 2 Z-up
plane, 6 views of 128² with a 45° field of view from 2.9 units, 4 point lights of 6 at 2.6 units,
64² maps, metallic 0) but its own truth maps and camera and light elevations (data_synth's
``peer-plane``). Mitsuba's targets are not written as a pbrfit capture because its ``principled``
BSDF is not the glTF BRDF pbrfit fits (Burley's diffuse with its retro-reflection, not Lambert's)
and its targets carry the noise of 128 samples per pixel: a fit of them would measure the model
mismatch, not the solver. Both whole-process times include each tool's own target making
(pbrfit's synth is run before, outside its time; Mitsuba's target renders are inside its).

    python experiments/peers/mitsuba.py [--iters 300] [--time-limit 600] [--work DIR]
                                        [--out experiments/results/peer_mitsuba.json]

``--iters`` and ``--time-limit`` pass to the peer script (its defaults: the reference run).
Mitsuba runs on the ``llvm_ad_rgb`` variant; drjit needs LLVM 16 or newer, found through
``DRJIT_LIBLLVM_PATH`` (set here to `LIBLLVM` when unset and present). Writes the JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent))
from speed import PEER_FIT, RESULTS, checked, pbrfit_command, run_timed, write_json  # noqa: E402

PEER_SCRIPT = HERE / "mitsuba_peer_fit.py"
#: Debian's LLVM 19 (apt-get install libllvm19), new enough for drjit.
LIBLLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
#: The reference run's optimisation settings (the peer script's own defaults).
REFERENCE = dict(iters=300, time_limit=600.0)


def run_pbrfit(work: Path, pbrfit: str) -> dict:
    """Synthesize the peer scene and time a cold `pbrfit fit` of it."""
    capture, cache, out = work / "peer-plane", work / "pbrfit-cache", work / "pbrfit-fit"
    checked(run_timed([pbrfit, "synth", "peer-plane", "--out", str(capture), "--noise", "0", "--quiet"]),
            "pbrfit synth peer-plane")
    cache.mkdir()
    run = checked(run_timed([pbrfit, "fit", str(capture), "--out", str(out), "--cache", str(cache), "--quiet",
                             *PEER_FIT]), "pbrfit fit")
    report = json.loads((out / "report.json").read_text())
    rmse = report["truth_rmse"]
    return dict(wall_s=run["wall_s"], peak_rss_mib=run["peak_rss_mib"], fit_wall_s=report["wall_time"],
                steps=report["steps"], times=report["times"], base_rmse=rmse["base_color"],
                roughness_rmse=rmse["roughness"], metallic_rmse=rmse["metallic"],
                rmse_over="observed texels", images="pbrfit's renders of data_synth's peer-plane, noiseless")


def run_mitsuba(work: Path, iters: int, time_limit: float) -> dict:
    """Time the Mitsuba peer script in a new process and read its results."""
    env = dict(os.environ)
    if "DRJIT_LIBLLVM_PATH" not in env and Path(LIBLLVM).exists():
        env["DRJIT_LIBLLVM_PATH"] = LIBLLVM
    out = work / "mitsuba"
    # -P: the script's folder is not put on sys.path, where this file would stand in for the mitsuba package
    cmd = [sys.executable, "-P", str(PEER_SCRIPT), "--out", str(out), "--iters", str(iters), "--time-limit", str(time_limit)]
    run = checked(run_timed(cmd, env), "the Mitsuba peer fit")
    info = json.loads((out / "peer_fit_results.json").read_text())
    last = info["rows"][-1]
    return dict(wall_s=run["wall_s"], peak_rss_mib=run["peak_rss_mib"], iters_done=info["iters_done"],
                optimisation_s=info["total_opt_s"], targets_s=info["t_targets_s"], load_s=info["t_load_s"],
                median_iter_s=info["median_iter_s"], base_rmse=last["base_rmse_vis"],
                roughness_rmse=last["rough_rmse_vis"], rmse_over="texels some view sees",
                flat_start=info["flat_start"], versions=dict(mitsuba=info["mitsuba"], drjit=info["drjit"]),
                variant=info["variant"], threads=info["threads"], llvm=info["llvm"], config=info["config"],
                images="Mitsuba's prb renders at 128 spp of the peer script's own truth maps")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--iters", type=int, default=REFERENCE["iters"], help="Mitsuba's Adam iterations (default: the reference run's)")
    p.add_argument("--time-limit", type=float, default=REFERENCE["time_limit"],
                   help="Mitsuba's optimisation wall-time limit in seconds (default: the reference run's)")
    p.add_argument("--work", default=None, help="folder for the capture, fits and Mitsuba's output (default: a temporary one)")
    p.add_argument("--out", default=str(RESULTS / "peer_mitsuba.json"), help="JSON to write")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.iters < 1:
        parser.error(f"--iters: expected 1 or more, got {args.iters}")
    if not args.time_limit > 0:
        parser.error(f"--time-limit: expected seconds > 0, got {args.time_limit}")
    if Path(args.out).suffix != ".json":
        parser.error(f"--out: expected a .json path, got {args.out}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="pbrfit-peer-"))
    work.mkdir(parents=True, exist_ok=True)
    for sub in ("peer-plane", "pbrfit-cache", "pbrfit-fit", "mitsuba"):
        if (work / sub).exists():
            raise SystemExit(f"mitsuba.py: {work / sub}: exists; give an empty --work folder")
    from solvers import machine

    pbrfit = run_pbrfit(work, pbrfit_command())
    print(f"pbrfit: {pbrfit['wall_s']:.1f} s, base {pbrfit['base_rmse']:.4f}, roughness {pbrfit['roughness_rmse']:.4f}",
          flush=True)
    mitsuba = run_mitsuba(work, args.iters, args.time_limit)
    print(f"Mitsuba: {mitsuba['wall_s']:.1f} s ({mitsuba['iters_done']} iterations), base {mitsuba['base_rmse']:.4f}, "
          f"roughness {mitsuba['roughness_rmse']:.4f}", flush=True)
    ratio = mitsuba["wall_s"] / pbrfit["wall_s"]
    print(f"Mitsuba / pbrfit whole-process time: {ratio:.1f}")
    reference = args.iters == REFERENCE["iters"] and args.time_limit == REFERENCE["time_limit"]
    write_json(dict(machine=machine(), reference_settings=reference, pbrfit=pbrfit, mitsuba=mitsuba,
                    time_ratio_mitsuba_over_pbrfit=ratio,
                    same_images=False, note=__doc__.split("\n\n")[2].replace("\n", " ")), Path(args.out))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
