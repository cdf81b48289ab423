"""A fit as `pbrfit fit` and `pbrfit demo` run it: a live progress line on a terminal
(`FitProgress`), the fit, its errors against `truth/` when the capture has one, and its output
folder with the convergence plot of the steps kept (`run_fit`, `loss_history`)."""

from __future__ import annotations

import sys

from ..errors import CaptureError

__all__ = ["FitProgress", "loss_history", "run_fit"]


class FitProgress:
    """A live line (rich) with level, step, loss and elapsed time (before the solve, the per-pixel IBL
    integrals' progress); also keeps the loss history."""

    def __init__(self, enabled: bool):
        import time

        self.history = []
        self._start = time.perf_counter()
        self._clock = time.perf_counter
        self._live = None
        if enabled and sys.stderr.isatty():
            from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

            self._live = Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                                  transient=True)
            self._task = self._live.add_task("fitting")
            self._live.start()

    def __call__(self, info: dict) -> None:
        if info.get("stage") == "ibl":  # the per-pixel integrals before the solve: no loss yet
            if self._live is not None:
                self._live.update(self._task, description=f"per-pixel IBL {info['done']:,} / {info['total']:,} pixels")
            return
        self.history.append(dict(info, time=self._clock() - self._start))
        if self._live is not None:
            h, w = info["resolution"]
            n = info.get("footprint")  # the auto footprint's two finishes: centres, then samples
            where = "" if n is None else ("  pixel centres" if n == 1 else f"  {n}x{n} samples")
            if "repair" in info:
                where += f"  repair {info['repair']}"
            if info.get("weighted"):
                where += "  weighted"
            if "check" in info:
                where += f"  uniform {info['check']}?"
            self._live.update(self._task, description=(
                f"level {info['level']} ({h}x{w}){where} step {info['step']:3d}  loss {info['loss']:.4e}"))

    def close(self) -> None:
        if self._live is not None:
            self._live.stop()


def loss_history(steps: list, report: dict) -> list:
    """The convergence plot's (step, loss) points: every step reported, but of the automatic
    footprint's two finishes (entries tagged "footprint") only the kept one's, of the repair's
    passes (tagged "repair", numbered from 1) only the kept ones', and of the uniform check's
    re-fits (tagged "check") only those of a channel made uniform. With an estimated noise level
    only the weighted fit's steps (tagged "weighted"): its loss is of the weighted residuals, on
    another scale than the first fit's."""
    from ..fitting.stages.selection import uniform_channels

    if any(h.get("weighted") for h in steps):
        steps = [h for h in steps if h.get("weighted")]
    kept = report.get("footprint", {}).get("selected")
    uniform = set(uniform_channels(report))
    passes = (report.get("repair") or {}).get("passes", [])
    repaired = {i + 1 for i, p in enumerate(passes) if p.get("kept")}

    def plotted(h) -> bool:
        return (h.get("footprint", kept) == kept and h.get("repair", None) in repaired | {None}
                and h.get("check", None) in uniform | {None})

    return [dict(step=i, loss=h["loss"]) for i, h in enumerate(h for h in steps if plotted(h))]


def run_fit(capture, out, options, cache_dir=None, quiet: bool = False):
    """Fit `capture` with `options` (a `pbrfit.FitOptions`), add truth errors to the report when `truth/` exists, write `out`; return
    (result, per-map RMSE or None)."""
    import numpy as np

    from ..fitting.api import fit, map_rmse
    from ..io.material_files import read_material
    from ..io.outputs import write_fit_output

    truth = None
    if capture.truth_dir is not None:  # read first: only evaluation uses it, so a bad one is skipped
        try:
            truth = read_material(capture.truth_dir)
        except CaptureError as err:
            print(f"pbrfit: warning: {err}; truth/ ignored (no truth_rmse)", file=sys.stderr)
    progress = FitProgress(not quiet)
    try:
        result = fit(capture, options, cache_dir=cache_dir, progress=progress)
    finally:
        progress.close()
    errors = None
    if truth is not None:
        errors = map_rmse(truth, result)
        result.report["truth_rmse"] = errors
    history = loss_history(progress.history, result.report)
    normals = result.material.normal is not None
    if normals:  # uncertainty.exr holds the spec's five channels; the slopes' σ goes to the report
        sig = np.asarray(result.uncertainty)[..., 5:7]
        seen = np.asarray(result.coverage) > 0
        result.report["normal_slope_sigma_median"] = float(np.median(sig[seen])) if seen.any() else float("nan")
    write_fit_output(
        out, capture, result.material, np.asarray(result.uncertainty)[..., :5], result.coverage, result.report,
        targets=list(zip(result.targets, result.masks)), renders=result.images, history=history,
        write_normal=normals,
    )
    return result, errors
