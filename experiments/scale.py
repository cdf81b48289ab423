"""Scale: the peer layout at growing sizes, 16 views of N² fitting N² maps, as one whole
`pbrfit fit` process each: wall time, peak memory, the report's time split, steps and truth RMSE.

Per N in ``--sizes``:

- the capture: ``pbrfit synth peer-plane --out CAP --size N --views 16 --texture-size N --noise 0
  --quiet`` (the peer scene's 2 × 2 plane and 4 point lights, noiseless, 16 views of N² and N²
  truth maps), its wall time and peak memory recorded too;
- the fit, cold: ``pbrfit fit CAP --out OUT --resolution N --quiet --cache EMPTY`` in a new
  process: launch-to-exit wall time, the child's peak resident memory (``os.wait4``'s rusage),
  and from its ``report.json`` the time split (``times``), the steps, the pixels fitted and the
  per-map RMSE against ``truth/`` (``truth_rmse``). With ``--gpu-memory`` the GPU's used memory
  is read from ``nvidia-smi`` every 0.2 s during the fit (the child runs with
  ``XLA_PYTHON_CLIENT_PREALLOCATE=false``, so the figure is what JAX holds, not its
  preallocated pool) and its peak recorded.

Then the peak memory's growth: a least-squares line through (image pixels 16 N², peak RSS) over
the sizes, its slope in bytes per image pixel, and the slope between each pair of neighbouring
sizes (equal slopes: linear growth).

    python experiments/scale.py [--sizes 128 256 512] [--views 16] [--timeout 1800]
                                [--gpu-memory] [--out experiments/results/scale.json]

The JSON is written again after each size, so a run stopped part way keeps the sizes done. Fits
run one after another, never two at once. On the shared 2-core CPU 128, 256 and 512 took 80
minutes together, 512 65 of them (experiments/speed.md, "Scale").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
#: The issue's scale target: 16 views of 1024² fitting 1024² maps within these.
TARGET = dict(wall_s=120.0, peak_rss_gib=8.0, base_color=0.01, roughness=0.03)
MIB = 1024.0 * 1024.0


def gpu_used_mib() -> float | None:
    """The GPU's used memory in MiB (the sum over GPUs), from ``nvidia-smi``; None without one."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0:
        return None
    return float(sum(float(x) for x in out.stdout.split()))


class GpuPeak:
    """The largest `gpu_used_mib` read every ``period`` seconds on a thread between start and stop."""

    def __init__(self, period: float = 0.2):
        self.period, self.peak, self._stop = period, None, threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def _poll(self) -> None:
        while not self._stop.is_set():
            used = gpu_used_mib()
            if used is not None:
                self.peak = used if self.peak is None else max(self.peak, used)
            self._stop.wait(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def run_measured(cmd: list, env: dict, timeout: float, gpu: bool = False) -> dict:
    """Run ``cmd`` in ``env`` to its end or ``timeout`` seconds (then killed): launch-to-exit wall
    seconds, the child's processor seconds (user + system) and peak resident memory (MiB, both
    ``os.wait4``'s rusage), its exit status, the last of its
    stderr and, with ``gpu``, the peak GPU memory used meanwhile (MiB)."""
    with tempfile.TemporaryFile("w+") as err:
        baseline = gpu_used_mib() if gpu else None
        with (GpuPeak() if gpu else _Nothing()) as poll:
            t = time.perf_counter()
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
            killed = False
            while True:
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    break
                if time.perf_counter() - t > timeout and not killed:
                    proc.kill()
                    killed = True
                time.sleep(0.05)
            wall = time.perf_counter() - t
        err.seek(0)
        row = dict(wall_s=wall, cpu_s=usage.ru_utime + usage.ru_stime, peak_rss_mib=usage.ru_maxrss / 1024.0,
                   rc=os.waitstatus_to_exitcode(status),
                   timed_out=killed, stderr_tail=err.read()[-2000:])
        if gpu:
            row.update(gpu_baseline_mib=baseline, gpu_peak_mib=poll.peak)
        return row


class _Nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


#: The fit's child: the `pbrfit` console script's own entry (``main()`` on ``sys.argv``), with the
#: command line's progress object (`pbrfit.cli.fit.FitProgress`, which a --quiet fit still calls at
#: every solver step) also appending each call, stamped with the wall clock, to a file (argv[1]):
#: where a fit stopped by the timeout had got to, and when its first step came.
TRACED = r"""
import json, sys, time
import pbrfit.cli.fit as cli_fit
from pbrfit.cli.main import main
trace = open(sys.argv[1], "a", buffering=1)
plain = cli_fit.FitProgress.__call__
def traced(self, info):
    trace.write(json.dumps(dict(info, clock=time.time()), default=str) + "\n")
    return plain(self, info)
cli_fit.FitProgress.__call__ = traced
sys.argv = ["pbrfit", *sys.argv[2:]]
sys.exit(main())
"""


def trace_summary(path: Path, launched: float) -> dict:
    """The progress trace read back: seconds from launch to the first and the last solver step,
    the steps reported per phase (main solve, repair passes, uniform check re-fits) and the last
    entry (where a stopped fit was)."""
    if not path.exists():
        return {}
    entries = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    if not entries:
        return dict(steps_reported=0)
    phase = lambda e: "repair" if "repair" in e else "check" if "check" in e else "main"  # noqa: E731
    counts = {}
    for e in entries:
        counts[phase(e)] = counts.get(phase(e), 0) + 1
    last = {k: v for k, v in entries[-1].items() if k != "clock"}
    return dict(first_step_s=entries[0]["clock"] - launched, last_step_s=entries[-1]["clock"] - launched,
                steps_reported=counts, last=last,
                per_phase_s={p: [min(e["clock"] for e in entries if phase(e) == p) - launched,
                                 max(e["clock"] for e in entries if phase(e) == p) - launched] for p in counts})


def growth(rows: list) -> dict:
    """Peak RSS against image pixels: the least-squares line's slope (bytes per image pixel) and
    intercept (MiB), and the slope between neighbouring sizes."""
    done = [r for r in rows if r.get("fit", {}).get("rc") == 0]
    if len(done) < 2:
        return {}
    px = np.array([r["image_pixels"] for r in done], float)
    rss = np.array([r["fit"]["peak_rss_mib"] * MIB for r in done], float)
    slope, intercept = np.polyfit(px, rss, 1)
    pairs = [dict(sizes=[done[i]["size"], done[i + 1]["size"]],
                  bytes_per_pixel=float((rss[i + 1] - rss[i]) / (px[i + 1] - px[i])))
             for i in range(len(done) - 1)]
    return dict(bytes_per_image_pixel=float(slope), intercept_mib=float(intercept / MIB), pairs=pairs,
                max_residual_mib=float(np.max(np.abs(rss - (slope * px + intercept))) / MIB))


def verdict(row: dict) -> dict:
    """Each of the issue's four targets met or not (None where not measured)."""
    fit = row.get("fit", {})
    rmse = row.get("truth_rmse") or {}
    ok = fit.get("rc") == 0
    return dict(wall=ok and fit["wall_s"] <= TARGET["wall_s"],
                memory=ok and fit["peak_rss_mib"] / 1024.0 <= TARGET["peak_rss_gib"],
                base_color=None if "base_color" not in rmse else rmse["base_color"] <= TARGET["base_color"],
                roughness=None if "roughness" not in rmse else rmse["roughness"] <= TARGET["roughness"])


def measure(size: int, views: int, work: Path, env: dict, timeout: float, gpu: bool) -> dict:
    """Synthesize the capture of ``views`` views of ``size``² and fit ``size``² maps, cold."""
    cap, out, cache = work / f"cap{size}", work / f"fit{size}", work / f"cache{size}"
    shutil.rmtree(cache, ignore_errors=True)
    pbrfit = [sys.executable, "-m", "pbrfit.cli.main"]
    row = dict(size=size, views=views, image_pixels=views * size * size)
    synth = run_measured([*pbrfit, "synth", "peer-plane", "--out", str(cap), "--size", str(size), "--views", str(views),
                          "--texture-size", str(size), "--noise", "0", "--quiet"], env, timeout)
    row["synth"] = {k: synth[k] for k in ("wall_s", "cpu_s", "peak_rss_mib", "rc")}
    if synth["rc"] != 0:
        row["synth"]["stderr_tail"] = synth["stderr_tail"]
        return row
    trace = work / f"trace{size}.jsonl"
    trace.unlink(missing_ok=True)
    launched = time.time()
    fit = run_measured([sys.executable, "-c", TRACED, str(trace), "fit", str(cap), "--out", str(out), "--resolution",
                        str(size), "--quiet", "--cache", str(cache)], env, timeout, gpu)
    row["fit"] = {k: v for k, v in fit.items() if k != "stderr_tail" or fit["rc"] != 0}
    row["trace"] = trace_summary(trace, launched)
    if fit["rc"] == 0:
        report = json.loads((out / "report.json").read_text())
        row.update({k: report.get(k) for k in ("steps", "iterations", "times", "truth_rmse", "pixels", "pixel_samples",
                                               "observed_texels", "resolution", "devices", "wall_time", "levels",
                                               "stages")})
    row["meets"] = verdict(row)
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(cache, ignore_errors=True)
    return row


def line(row: dict) -> str:
    fit, t, rmse = row.get("fit", {}), row.get("times") or {}, row.get("truth_rmse") or {}
    gpu = f"  gpu {fit['gpu_peak_mib']:.0f} MiB" if fit.get("gpu_peak_mib") is not None else ""
    if fit.get("rc") != 0:
        return f"N={row['size']}: failed {fit or row['synth']}"
    split = " ".join(f"{k} {v:.1f}" for k, v in t.items())
    return (f"N={row['size']}: synth {row['synth']['wall_s']:.1f} s; fit {fit['wall_s']:.1f} s ({fit['cpu_s']:.0f} processor s), "
            f"peak {fit['peak_rss_mib']:.0f} MiB{gpu}, {row['steps']} steps, pixels {row['pixels']}, "
            f"base {rmse.get('base_color', float('nan')):.2e} rough {rmse.get('roughness', float('nan')):.2e} "
            f"metal {rmse.get('metallic', float('nan')):.2e}\n    times: {split}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512], help="image and map sizes N (default 128 256 512)")
    p.add_argument("--views", type=int, default=16, help="views per capture (default 16)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds after which a synth or fit is stopped (default 1800)")
    p.add_argument("--gpu-memory", action="store_true", help="read the GPU's peak used memory with nvidia-smi during each fit")
    p.add_argument("--work", default=None, help="folder for the captures and fits (default: a temporary one)")
    p.add_argument("--out", default=str(RESULTS / "scale.json"), help="JSON to write")
    args = p.parse_args(argv)
    if any(n < 8 for n in args.sizes) or args.views < 1:
        p.error("--sizes: expected 8 or more; --views: 1 or more")
    env = dict(os.environ)
    if args.gpu_memory:
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    out = Path(args.out)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="pbrfit-scale-"))
    work.mkdir(parents=True, exist_ok=True)
    results = dict(machine=dict(platform=platform.platform(), processor=platform.processor(), cpus=os.cpu_count(),
                                gpu=gpu_used_mib() is not None),
                   target=TARGET, views=args.views, rows=[])
    try:
        for n in args.sizes:
            row = measure(n, args.views, work, env, args.timeout, args.gpu_memory)
            results["rows"].append(row)
            results["growth"] = growth(results["rows"])
            out.parent.mkdir(parents=True, exist_ok=True)
            tmp = out.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(results, indent=1) + "\n")
            tmp.replace(out)
            print(line(row), flush=True)
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    g = results.get("growth") or {}
    if g:
        pairs = ", ".join(f"{a}->{b}: {q['bytes_per_pixel']:.0f}" for (a, b), q in ((q["sizes"], q) for q in g["pairs"]))
        print(f"peak RSS: {g['bytes_per_image_pixel']:.0f} bytes per image pixel + {g['intercept_mib']:.0f} MiB "
              f"(pairs {pairs})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
