"""Speed: how long pbrfit takes the way users run it, where the time goes, and how far a solver
step is from the arithmetic it must do.

Each scene is a `pbrfit synth PRESET --out DIR --quiet` capture, noiseless (``--noise 0``), and
the peer scene also with 1% noise: additive Gaussian of std 1% of the mean linear pixel value
over the mesh. `pbrfit synth --noise S` adds std S to the display values, which for the peer's
linear EXR images are the linear values, so the script writes the noiseless peer first, measures
the mean over its masks and writes the noisy one with ``--noise 0.01 * mean`` (about 0.0025).

Per scene and rung (a set of extra `pbrfit fit` arguments, `--rungs`), repeated ``--repeats``
times:

- cold: ``pbrfit fit CAP --out OUT --cache EMPTY`` in a new process (the peer at
  ``--resolution 64``, the rest at their default map size): launch-to-exit wall time and peak
  resident memory (the child's rusage from ``os.wait4``);
- warm: the same command again with the same, now filled, ``--cache`` (G-buffers and XLA
  executables on disk);
- script: one Python process (a subprocess of this one, so each scene starts clean) that loads
  the capture and calls ``pbrfit.fit(capture, options)`` twice with the same options (made by the
  command line's own `pbrfit.cli.fit.fit_options`, no cache folder, as a library user calls it):
  both calls' wall times, the second being the in-process warm figure;
- from the cold run's ``report.json``: the time split (``times``: setup, compile waited for,
  compile overlapped in the background, init, search, solve, repair, uniform_check,
  unconstrained, post, other), the steps and the per-map RMSE against ``truth/`` (``truth_rmse``).

With more than one rung, each later rung's cold, warm and script times as fractions of the first
rung's (``ladder`` in the JSON, and printed): the speed ladder's ratios.

Once per run: ``pbrfit --help``, ``pbrfit fit --help``, ``python -c "import pbrfit"`` and
``python -c "import pbrfit.cli.main"`` wall times, and the machine's dense float32 rate (a numpy
matrix product, `machine_rate`).

The arithmetic floor of a solver step (`step_flops`, counted from the problem's size: P pixels,
S samples per pixel, L punctual lights, an environment or not, K = 5 channels, T texels, c
conjugate-gradient iterations per step, all from the report) is set against the measured
``times["solve"]`` / solve steps; the floor's time is the count divided by the dense rate, an
optimistic bound (shading is elementwise with divisions, square roots and gathers, not FMAs).

    python experiments/speed.py [--scenes peer-plane peer-plane-noise demo] [--repeats 1]
                                [--extra-args "--cg-rtol 1e-2"] [--rungs default= lean="--no-search --no-repair"]
                                [--out experiments/results/speed.json]

Writes the JSON (default experiments/results/speed.json) and a chart beside it (speed.png),
printing a table as it goes; ``--plot-only`` redraws the chart from the JSON. An argument
string that starts with a dash and holds no space is given with ``=``: ``--extra-args=--no-search``. Every fit runs one after another: never two at once, as a shared
CPU's timings would mix. On a shared 2-core CPU the peer scene and the demo take 7 minutes (one
rung, one repeat); the five scenes roughly 25.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from solvers import machine  # noqa: E402

RESULTS = Path(__file__).parent / "results"


@dataclass(frozen=True)
class Scene:
    """A benchmark scene: the data_synth preset, `pbrfit synth` arguments, the noise as a share
    of the mean linear pixel value over the mesh (0: none) and the scene's own `pbrfit fit` arguments."""

    preset: str
    synth: tuple = ("--noise", "0")
    noise_share: float = 0.0
    fit: tuple = ()


#: The peer's map size, as the fitting issue fits it.
PEER_FIT = ("--resolution", "64")
#: "1% noise": the std as a share of the mean linear pixel value over the mesh.
NOISE_SHARE = 0.01
SCENES = {
    "peer-plane": Scene("peer-plane", fit=PEER_FIT),
    "peer-plane-noise": Scene("peer-plane", noise_share=NOISE_SHARE, fit=PEER_FIT),
    "plane-flash": Scene("plane-flash"),
    "demo": Scene("demo"),
    "sphere-env": Scene("sphere-env"),
}
#: The report's time split, in the order the table and chart give it.
SPLIT = ("setup", "compile", "compile_background", "init", "search", "solve", "repair", "uniform_check",
         "unconstrained", "post", "other")

# --- the arithmetic of one solver step (FLOPs; see step_flops) --------------------------------
#: Channels per texel: base R, G, B, metallic, roughness.
K = 5
#: One punctual light's value at one point: light vector and distance (8), normalising l and
#: h = v + l (17), the cosines n·l, n·h, v·h (15), GGX D (8), height-correlated Smith V (14),
#: Schlick F with F0 from base colour and metallic (20), Lambert diffuse (9), the sum times the
#: light's radiance and n·l (19).
F_LIGHT = 110
#: The split-sum environment at one point: the irradiance lookup (75), the reflected direction
#: (10), its lat-long coordinates (40), the prefiltered mips' trilinear taps (60), the BRDF LUT
#: (20) and the sum (20).
F_ENV = 225
#: Per sample: exposure, tone map, encoding and residual of three channels.
F_PIXEL = 30
#: Sampling the material at a sample's uv: 4 bilinear taps of K channels, and the weights.
F_SAMPLE = 2 * 4 * K + 10
#: Forward mode: each of the K tangents costs about two FLOPs per FLOP of the value (products'
#: rule a db + b da), so value and tangents cost (1 + 2 K) times the value.
TANGENT_FACTOR = 1 + 2 * K
#: Per sample row: g += Jᵀr (2·3K), JᵀJ (2·3K²), both weighted into 4 taps (2·4(K + K²)).
F_BLOCKS = 2 * 3 * K + 2 * 3 * K * K + 2 * 4 * (K + K * K)
#: Per texel per step: damping and inverting its K × K block (about 2K³).
F_INVERT = 2 * K**3
#: One CG product JᵀJ v per sample row: gather 4 taps (2·4K), J v (2·3K), Jᵀ(·) (2·3K), scatter (2·4K).
F_PRODUCT = 2 * 4 * K + 2 * 3 * K + 2 * 3 * K + 2 * 4 * K
#: Per texel per CG iteration: the block preconditioner (2K²) and five vector updates (2·5K).
F_CG_TEXEL = 2 * K * K + 2 * 5 * K


def step_flops(pixels: int, samples: int, lights: float, environment: bool, texels: int, cg_per_step: float) -> float:
    """FLOPs of one structured Levenberg-Marquardt step (`pbrfit.fitting.solvers.structured`), from
    the problem's size. With R = pixels · samples sample rows and a point's shading cost
    F = L · F_LIGHT + [env] F_ENV + F_PIXEL:

        linearise   R (TANGENT_FACTOR · F + F_SAMPLE)        value and K tangents, forward mode
        blocks      R · F_BLOCKS + T · F_INVERT              gradient, diagonal blocks, their inverses
        CG          c (R · F_PRODUCT + T · F_CG_TEXEL)       c products JᵀJ v and their vector work
        trial       R (F + F_SAMPLE)                         the loss at the trial point

    An estimate to the nearest factor of two: the per-light count is the glTF BRDF's operations
    (Filament's `brdf.fs` terms), a square root or division counting one."""
    rows = pixels * samples
    shade = lights * F_LIGHT + (F_ENV if environment else 0) + F_PIXEL
    linearise = rows * (TANGENT_FACTOR * shade + F_SAMPLE)
    blocks = rows * F_BLOCKS + texels * F_INVERT
    cg = cg_per_step * (rows * F_PRODUCT + texels * F_CG_TEXEL)
    trial = rows * (shade + F_SAMPLE)
    return float(linearise + blocks + cg + trial)


def machine_rate(size: int = 1024, repeats: int = 5) -> float:
    """The best of ``repeats`` float32 ``size``² matrix products (numpy's BLAS), in FLOP/s: the
    dense rate the floor divides by (2 size³ FLOPs each)."""
    rng = np.random.default_rng(0)
    a = rng.random((size, size), np.float32)
    b = rng.random((size, size), np.float32)
    a @ b
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t)
    return 2.0 * size**3 / best


# --- processes --------------------------------------------------------------------------------


def run_timed(cmd: list, env=None) -> dict:
    """Run ``cmd`` to its end (in ``env``, default this process's): wall seconds from launch to
    exit, the child's peak resident memory (MiB, ``os.wait4``'s rusage) and its exit status;
    stdout and stderr kept (text)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return dict(wall_s=wall, peak_rss_mib=usage.ru_maxrss / 1024.0, rc=proc.returncode,
                    stdout=out.read(), stderr=err.read())


def checked(run: dict, what: str) -> dict:
    """``run``, or a one-line error naming ``what`` and the child's last line of stderr."""
    if run["rc"] != 0:
        last = (run["stderr"].strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"{Path(sys.argv[0]).name}: {what} failed (exit {run['rc']}): {last}")
    return run


def pbrfit_command() -> str:
    """The `pbrfit` command users run (beside this Python, else on PATH)."""
    beside = Path(sys.executable).with_name("pbrfit")
    found = str(beside) if beside.exists() else shutil.which("pbrfit")
    if not found:
        raise SystemExit("speed.py: no `pbrfit` command beside this Python or on PATH (pip install -e .)")
    return found


def mean_mesh_value(capture: Path) -> float:
    """The mean linear pixel value over the masks of a capture's frames (every channel), for
    linear images only (there display and linear values agree, so `pbrfit synth --noise` is in
    linear units)."""
    from pbrfit.io.images import read_image

    spec = json.loads((capture / "capture.json").read_text())
    if spec.get("images", {}).get("tonemap", "none") != "none":
        raise SystemExit(f"speed.py: {capture}: noise as a share of linear values needs untonemapped images")
    total, count = 0.0, 0
    for frame in spec["frames"]:
        image, info = read_image(capture / frame["file_path"])
        if not frame["file_path"].endswith((".exr", ".hdr")):
            raise SystemExit(f"speed.py: {capture / frame['file_path']}: noise as a share of linear values needs linear images")
        mask, _ = read_image(capture / frame["mask_path"])
        on = (mask[..., 0] if mask.ndim == 3 else mask) > 0
        total += float(np.sum(image[on][:, :3], dtype=np.float64))
        count += int(on.sum()) * 3
    return total / count


def synthesize(name: str, scene: Scene, root: Path, pbrfit: str) -> tuple[Path, dict]:
    """Write the scene's capture under ``root``; returns it and what was done (the noise std)."""
    clean = root / f"{scene.preset}-clean"
    if not (clean / "capture.json").exists():
        checked(run_timed([pbrfit, "synth", scene.preset, "--out", str(clean), "--quiet", *scene.synth]),
                f"pbrfit synth {scene.preset}")
    if not scene.noise_share:
        return clean, dict(noise_std=0.0)
    mean = mean_mesh_value(clean)
    std = scene.noise_share * mean
    noisy = root / name
    synth = [a for a in scene.synth]
    i = synth.index("--noise")
    synth[i + 1] = repr(std)
    checked(run_timed([pbrfit, "synth", scene.preset, "--out", str(noisy), "--quiet", *synth]),
            f"pbrfit synth {scene.preset} --noise {std}")
    return noisy, dict(noise_std=std, mean_mesh_value=mean, noise_share=scene.noise_share)


#: The in-process run: the capture loaded once, two `pbrfit.fit` calls with the command line's
#: options (argv: capture, then `pbrfit fit` arguments); prints one JSON line.
SCRIPT = r"""
import json, sys, time
t = time.perf_counter()
import pbrfit
from pbrfit.cli.fit import fit_options
from pbrfit.cli.main import build_parser
imported = time.perf_counter() - t
capture_dir, fit_args = sys.argv[1], sys.argv[2:]
options = fit_options(build_parser().parse_args(["fit", capture_dir, "--out", "unused", *fit_args]))
capture = pbrfit.load_capture(capture_dir)
calls = []
for _ in range(2):
    t = time.perf_counter()
    result = pbrfit.fit(capture, options)
    calls.append(dict(wall_s=time.perf_counter() - t, steps=result.report["steps"], times=result.report["times"]))
print(json.dumps(dict(import_s=imported, calls=calls)))
"""


def capture_lights(capture: Path) -> tuple[float, bool]:
    """(punctual lights per frame, on average: global, the flash and the frame's own; whether an
    environment lights it), from capture.json."""
    spec = json.loads((capture / "capture.json").read_text())
    per_frame = [len(f.get("lights", [])) for f in spec["frames"]]
    lights = len(spec.get("lights", [])) + (1 if spec.get("flash") else 0) + sum(per_frame) / len(per_frame)
    return float(lights), "environment" in spec


def floor_row(report: dict, capture: Path, rate: float) -> dict:
    """The solve's measured seconds per step against `step_flops` / ``rate``."""
    levels = report["levels"]
    steps = sum(level["steps"] for level in levels)
    cg = sum(level.get("cg_iterations", 0) for level in levels)
    samples = report["pixel_samples"]
    samples = int(samples) ** 2 if isinstance(samples, int) else 1
    lights, environment = capture_lights(capture)
    texels = int(np.prod(report["resolution"]))
    flops = step_flops(report["pixels"], samples, lights, environment, texels, cg / max(steps, 1))
    measured = report["times"]["solve"] / max(steps, 1)
    floor = flops / rate
    return dict(solve_steps=steps, cg_per_step=cg / max(steps, 1), samples=samples, lights=lights,
                environment=environment, flops_per_step=flops, floor_s_per_step=floor,
                measured_s_per_step=measured, measured_over_floor=measured / floor,
                achieved_gflops=flops / measured / 1e9)


def measure(name: str, capture: Path, fit_args: list, pbrfit: str, rate: float, work: Path) -> dict:
    """One repeat of the cold, warm and in-process runs of one scene and rung."""
    cache = Path(tempfile.mkdtemp(prefix="cache-", dir=work))
    out = work / "fit"
    cmd = [pbrfit, "fit", str(capture), "--out", str(out), "--cache", str(cache), "--quiet", *fit_args]
    cold = checked(run_timed(cmd), f"cold pbrfit fit {name}")
    report = json.loads((out / "report.json").read_text())
    warm = checked(run_timed(cmd), f"warm pbrfit fit {name}")
    warm_report = json.loads((out / "report.json").read_text())
    script = checked(run_timed([sys.executable, "-c", SCRIPT, str(capture), *fit_args]), f"pbrfit.fit {name}")
    calls = json.loads(script["stdout"].strip().splitlines()[-1])
    shutil.rmtree(cache, ignore_errors=True)
    keep = lambda r: {k: r[k] for k in ("wall_s", "peak_rss_mib")}  # noqa: E731
    return dict(
        cold=dict(keep(cold), fit_wall_s=report["wall_time"], times=report["times"]),
        warm=dict(keep(warm), fit_wall_s=warm_report["wall_time"], times=warm_report["times"]),
        script=dict(keep(script), import_s=calls["import_s"], first_s=calls["calls"][0]["wall_s"],
                    second_s=calls["calls"][1]["wall_s"], second_times=calls["calls"][1]["times"]),
        steps=report["steps"], truth_rmse=report.get("truth_rmse"), resolution=report["resolution"],
        pixels=report["pixels"], pixel_samples=report["pixel_samples"], floor=floor_row(report, capture, rate),
    )


def startup_times(pbrfit: str, repeats: int) -> dict:
    """Median wall seconds of the help screens and the imports, each in a new process."""
    cmds = {"pbrfit --help": [pbrfit, "--help"], "pbrfit fit --help": [pbrfit, "fit", "--help"],
            "import pbrfit": [sys.executable, "-c", "import pbrfit"],
            "import pbrfit.cli.main": [sys.executable, "-c", "import pbrfit.cli.main"]}
    return {k: statistics.median(checked(run_timed(c), k)["wall_s"] for _ in range(repeats)) for k, c in cmds.items()}


# --- arguments, table, chart ------------------------------------------------------------------


def parse_rungs(items: list) -> dict:
    """``name=args`` pairs -> {name: [args]} (args split as a shell does; empty allowed)."""
    rungs = {}
    for item in items:
        name, sep, args = item.partition("=")
        if not sep or not name:
            raise argparse.ArgumentTypeError(f"--rungs: expected NAME=ARGS, got {item!r}")
        if name in rungs:
            raise argparse.ArgumentTypeError(f"--rungs: {name!r} given twice")
        try:
            rungs[name] = shlex.split(args)
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"--rungs: {name}: {e}") from None
    return rungs


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES), metavar="SCENE",
                   help=f"scenes to time, some of {', '.join(SCENES)} (default: all)")
    p.add_argument("--repeats", type=int, default=1, help="repeats of each measurement (default 1); the table gives medians")
    p.add_argument("--extra-args", default="", help="arguments added to every `pbrfit fit` (one string, split as a shell does)")
    p.add_argument("--rungs", nargs="+", default=["default="], metavar="NAME=ARGS",
                   help='named sets of `pbrfit fit` arguments, each timed: default= lean="--no-search --no-repair"')
    p.add_argument("--out", default=str(RESULTS / "speed.json"), help="JSON to write (the chart beside it, .png)")
    p.add_argument("--work", default=None, help="folder for the captures and fits (default: a temporary one)")
    p.add_argument("--plot-only", action="store_true", help="redraw the chart from the JSON at --out and stop")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats: expected 1 or more, got {args.repeats}")
    try:
        args.extra = shlex.split(args.extra_args)
        args.rung_args = parse_rungs(args.rungs)
    except (ValueError, argparse.ArgumentTypeError) as e:
        parser.error(str(e))
    if not Path(args.out).suffix == ".json":
        parser.error(f"--out: expected a .json path, got {args.out}")
    return args


COLUMNS = ("scene", "rung", "cold s", "warm s", "script 2nd s", "peak MiB", "steps", "compile", "overlap",
           "solve", "s/step", "floor s/step", "base", "rough")


def median_of(rows: list, f) -> float:
    """The median of ``f`` over the repeats ``rows``."""
    return statistics.median(f(r) for r in rows)


#: The three wall times of a run: the cold command, the warm command, a second call in a script.
TIMES = {"cold": lambda r: r["cold"]["wall_s"], "warm": lambda r: r["warm"]["wall_s"],
         "script": lambda r: r["script"]["second_s"]}


def table_line(scene: str, rung: str, rows: list) -> str:
    """One markdown table line: medians over the repeats."""
    med = lambda f: median_of(rows, f)  # noqa: E731
    rmse = rows[0]["truth_rmse"] or {}
    cells = (scene, rung, f"{med(lambda r: r['cold']['wall_s']):.1f}", f"{med(lambda r: r['warm']['wall_s']):.1f}",
             f"{med(lambda r: r['script']['second_s']):.1f}", f"{med(lambda r: r['cold']['peak_rss_mib']):.0f}",
             str(rows[0]["steps"]), f"{med(lambda r: r['cold']['times'].get('compile', 0)):.1f}",
             f"{med(lambda r: r['cold']['times'].get('compile_background', 0)):.1f}",
             f"{med(lambda r: r['cold']['times'].get('solve', 0)):.1f}",
             f"{med(lambda r: r['floor']['measured_s_per_step']):.3f}", f"{rows[0]['floor']['floor_s_per_step']:.4f}",
             f"{rmse.get('base_color', float('nan')):.4f}", f"{rmse.get('roughness', float('nan')):.4f}")
    return "| " + " | ".join(cells) + " |"


def ladder(results: dict) -> dict:
    """Per scene and rung after the first, each of its `TIMES` (median over the repeats) as a
    fraction of the first rung's: the speed ladder's ratios (the issue's target for draft: a
    quarter)."""
    out = {}
    for scene, entry in results["scenes"].items():
        rungs = list(entry["rungs"].items())
        (_, base), rest = rungs[0], rungs[1:]
        out[scene] = {rung: {k: median_of(rows, f) / median_of(base, f) for k, f in TIMES.items()}
                      for rung, rows in rest}
    return out


def plot(results: dict, path: Path) -> None:
    """Left: cold, warm and in-process second-call wall time per scene and rung; middle: the cold
    run's time split; right: the cold fit's RMSE against the truth per map (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [(s, r) for s in results["scenes"] for r in results["scenes"][s]["rungs"]]
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(17, 4.5))
    x = np.arange(len(keys))
    labels = dict(cold="cold command", warm="warm command", script="pbrfit.fit, 2nd call")
    for i, (name, f) in enumerate(TIMES.items()):
        a.bar(x + (i - 1) * 0.27, [median_of(results["scenes"][s]["rungs"][r], f) for s, r in keys], 0.27,
              label=labels[name])
    names = [f"{s}\n{r}" if len(results["rungs"]) > 1 else s for s, r in keys]
    a.set_xticks(x, names, rotation=20, fontsize=8)
    a.set_ylabel("wall time (s)")
    a.legend(fontsize=8)
    bottom = np.zeros(len(keys))
    for part in SPLIT:
        if part == "compile_background":  # overlapped: not part of the wall time
            continue
        h = np.array([median_of(results["scenes"][s]["rungs"][r], lambda q: q["cold"]["times"].get(part, 0.0))
                      for s, r in keys])
        b.bar(x, h, 0.6, bottom=bottom, label=part)
        bottom += h
    b.set_xticks(x, names, rotation=20, fontsize=8)
    b.set_ylabel("cold fit's time split (s)")
    b.legend(fontsize=7, ncol=2)
    for i, name in enumerate(("base_color", "metallic", "roughness")):
        # (an exact map's 0 drawn at the axis' floor)
        err = [max((results["scenes"][s]["rungs"][r][0]["truth_rmse"] or {}).get(name, np.nan), 1e-5) for s, r in keys]
        c.bar(x + (i - 1) * 0.27, err, 0.27, label=name)
    c.set_yscale("log")
    c.set_ylim(1e-5, 1.0)
    c.set_xticks(x, names, rotation=20, fontsize=8)
    c.set_ylabel("RMSE against the truth (floor 1e-5)")
    c.legend(fontsize=8)
    fig.suptitle(f"pbrfit speed ({results['machine']['processor']}, {results['machine']['cpu_count']} CPUs)", fontsize=9)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)


def write_json(data: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    out = Path(args.out)
    if args.plot_only:
        if not out.is_file():
            raise SystemExit(f"speed.py: {out}: no such results file to plot")
        plot(json.loads(out.read_text()), out.with_suffix(".png"))
        print(f"wrote {out.with_suffix('.png')}")
        return 0
    pbrfit = pbrfit_command()
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="pbrfit-speed-"))
    work.mkdir(parents=True, exist_ok=True)
    rate = machine_rate()
    results = dict(machine=machine(), dense_gflops=rate / 1e9, extra_args=args.extra, rungs=args.rung_args,
                   repeats=args.repeats, startup=startup_times(pbrfit, args.repeats), scenes={})
    print(f"dense float32 rate {rate / 1e9:.1f} GFLOP/s; " +
          "; ".join(f"{k} {v:.2f} s" for k, v in results["startup"].items()), flush=True)
    print("| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS), flush=True)
    for name in args.scenes:
        capture, synth = synthesize(name, SCENES[name], work, pbrfit)
        entry = results["scenes"][name] = dict(preset=SCENES[name].preset, synth=synth, rungs={})
        for rung, rung_args in args.rung_args.items():
            fit_args = [*SCENES[name].fit, *args.extra, *rung_args]
            rows = [measure(name, capture, fit_args, pbrfit, rate, work) for _ in range(args.repeats)]
            entry["rungs"][rung] = rows
            print(table_line(name, rung, rows), flush=True)
            write_json(results, out)
    results["ladder"] = ladder(results)
    first = next(iter(args.rung_args))
    for scene, rungs in results["ladder"].items():
        for rung, ratio in rungs.items():
            print(f"{scene}: {rung} takes " + " / ".join(f"{ratio[k]:.2f}" for k in TIMES)
                  + f" of {first}'s {' / '.join(TIMES)} time", flush=True)
    write_json(results, out)
    if importlib.util.find_spec("matplotlib") is None:
        print(f"wrote {out}; no chart: matplotlib is not installed (pip install -e '.[experiments]')")
        return 0
    plot(results, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
