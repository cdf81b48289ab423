"""`pbrfit fit` (`run`): its arguments' `pbrfit.FitOptions` with every refusal naming the flag
(`fit_options`; the flags are `pbrfit.cli.parser.add_fit`'s), the fit as `pbrfit fit` and
`pbrfit demo` run it (`run_fit`: a live progress line on a terminal, `FitProgress`; the errors
against `truth/` when the capture has one; the output folder with the convergence plot of the
steps kept, `loss_history`) and the summary line it prints (`fit_summary`)."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Optional

import jax
import numpy as np
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from .cache import cache_dir
from .model_flag import model_changes
from .parser import EXIT_OK, default_continuation
from .. import __version__
from ..errors import CaptureError
from ..fitting.checkpoint import Checkpoint, checkpoint_folder, folder_digests
from ..fitting.api import fit, map_rmse
from ..fitting.result import truth_at
from ..fitting.defaults import DEFAULT_SOLVER, MATERIAL_MAPS, MAX_PIXEL_SAMPLES
from ..fitting.options import FLOAT32_MAX, FitOptions, OptionNames
from ..fitting.runner import compile_summary
from ..fitting.stages.selection import uniform_channels
from ..io.atomic import check_not_inside, check_output_dir
from ..io.material_files import read_map, read_material
from ..io.outputs import write_fit_output
from ..lighting.settings import MAX_LEVELS, MAX_SAMPLES, MIN_LEVELS, MIN_SAMPLES, PixelIBLSettings
from ..lighting.visibility import OcclusionSettings
from ..scene.capture import load_capture

__all__ = ["run", "fit_options", "fit_summary", "describe", "FitProgress", "loss_history", "run_fit"]


def run(args) -> int:
    """`pbrfit fit` on its parsed arguments; returns the exit status."""
    options = fit_options(args)
    out = Path(args.out)
    check_output_dir(out, "fit")
    checkpoint = Checkpoint(checkpoint_folder(out), fit_fingerprint(args), resume=args.resume)
    options = options.replace(checkpoint=checkpoint)
    capture = load_capture(args.capture, require_uv=options.maps == "texture" or "normal" in options.fitted)
    check_not_inside(capture.root, out, "capture being fitted")
    for name in MATERIAL_MAPS:
        folder = getattr(args, f"{name}_from")
        if folder is not None:
            check_not_inside(folder, out, f"{name} map of --{name.replace('_', '-')}-from")
        if name not in options.fitted and name not in options.held and not args.quiet:
            print(f"pbrfit: note: {name} is neither fitted nor held (--fit, --{name.replace('_', '-')}): "
                  "it stays at the prior", file=sys.stderr)
    if args.ibl == "per_pixel" and capture.environment is None:
        print(f"pbrfit: warning: --ibl per_pixel: {capture.root} has no environment; nothing to integrate",
              file=sys.stderr)
    result, errors = run_fit(capture, out, options, cache_dir(args), args.quiet)
    checkpoint.remove()
    if not args.quiet:
        print(f"{fit_summary(result, errors)}; wrote {out}")
    return EXIT_OK


#: The arguments of `pbrfit fit` that do not change what it computes (left out of `fit_fingerprint`).
_NOT_FITTED = ("command", "out", "quiet", "resume", "cache", "no_cache")


def fit_fingerprint(args) -> dict:
    """What a checkpoint of this fit must match to be resumed (`pbrfit.fitting.checkpoint.Checkpoint`):
    pbrfit's version, every flag that changes the fit, and the bytes of the capture's files and of
    the material folders of ``--...-from``."""
    out = Path(args.out)
    options = {f"--{name.replace('_', '-')}": value for name, value in sorted(vars(args).items())
               if name not in _NOT_FITTED and not callable(value)}
    capture = Path(args.capture)
    folders = [("capture", capture if capture.is_dir() else capture.parent)]
    folders += [(f"--{name.replace('_', '-')}-from", getattr(args, f"{name}_from")) for name in MATERIAL_MAPS
                if getattr(args, f"{name}_from") is not None]
    files = {}
    for label, folder in folders:
        if Path(folder).exists():  # (one that does not is refused, named, where it is read)
            for rel, digest in folder_digests(folder, skip=(out, checkpoint_folder(out))).items():
                files[f"{label} {rel}"] = digest
    return {"pbrfit": __version__, "options": json.loads(json.dumps(options, default=str)), "files": files}


def fit_options(args):
    """The `pbrfit.FitOptions` of the command line (errors name the flag)."""
    fixed, held_by = {}, {}
    if args.base_color is not None:
        try:
            rgb = [float(c) for c in args.base_color.split(",")]
        except ValueError:
            rgb = []
        if len(rgb) != 3:
            raise CaptureError(f"--base-color: expected R,G,B in [0, 1], got {args.base_color!r}")
        fixed["base_color"], held_by["base_color"] = rgb, "--base-color"
    for name in ("metallic", "roughness"):
        if getattr(args, name) is not None:
            fixed[name], held_by[name] = getattr(args, name), f"--{name}"
    for name in MATERIAL_MAPS:
        folder = getattr(args, f"{name}_from")
        if folder is not None:
            flag = name.replace("_", "-")
            if name in fixed:
                raise CaptureError(f"--{flag}-from: --{flag} holds {name} at a value too; give one of the two")
            try:
                fixed[name], held_by[name] = read_map(folder, name), f"--{flag}-from"
            except CaptureError as err:  # the option that named the folder, then what is wrong with it
                raise CaptureError(f"--{flag}-from: {err}") from None
    continuation = _continuation(default_continuation() if args.continuation is None else args.continuation)
    # a flag a mode does not read is refused even at its default value (check_options, which sees
    # values only, refuses values other than the default)
    for flag, given in (("--cg-rtol", args.cg_rtol is not None), ("--noise-rtol", args.noise_rtol is not None),
                        ("--continuation", args.continuation is not None and bool(continuation))):
        if given and args.solver != DEFAULT_SOLVER:
            raise CaptureError(f"{flag}: only the {DEFAULT_SOLVER} solver uses it, not --solver {args.solver}")
        if given and flag == "--continuation" and args.maps == "none":
            raise CaptureError(f"{flag}: --maps none fits one uniform material (1 x 1 maps)")
    if args.loss_scale is not None and args.loss == "l2":
        raise CaptureError("--loss-scale: only a robust loss uses it (--loss huber or cauchy)")
    for name in ("ibl_samples", "ibl_levels"):
        if getattr(args, name) is not None and args.ibl == "split_sum":
            raise CaptureError(f"--{name.replace('_', '-')}: only per-pixel integrals use it (--ibl per_pixel, "
                               "or auto where it chooses them)")
    if args.bounce is not None and (args.ibl == "split_sum" or args.occlusion == "off"):
        raise CaptureError("--bounce: only per-pixel integrals with occlusion use it (not with "
                           f"{'--ibl split_sum' if args.ibl == 'split_sum' else '--occlusion off'})")
    pixel_samples = args.pixel_samples  # None: the --quality rung's, else auto
    if pixel_samples not in (None, "auto"):
        if not (pixel_samples.isascii() and pixel_samples.isdigit() and 1 <= int(pixel_samples) <= MAX_PIXEL_SAMPLES):
            raise CaptureError(f"--pixel-samples: expected auto or 1 to {MAX_PIXEL_SAMPLES}, got {args.pixel_samples}")
        pixel_samples = int(pixel_samples)
    for flag, value, least, most in (("--ibl-levels", args.ibl_levels, MIN_LEVELS, MAX_LEVELS),
                                     ("--ibl-samples", args.ibl_samples, MIN_SAMPLES, MAX_SAMPLES)):
        if value is not None and not least <= value <= most:
            raise CaptureError(f"{flag}: must be between {least} and {most}, got {value}")
    pixel_ibl_settings = PixelIBLSettings(
        levels=PixelIBLSettings.levels if args.ibl_levels is None else args.ibl_levels,
        samples=PixelIBLSettings.samples if args.ibl_samples is None else args.ibl_samples)
    devices = fit_devices(args.devices)
    options = dict(
        fit=args.fit, fixed=fixed, maps=args.maps, resolution=args.resolution, solver=args.solver,
        max_steps=args.max_steps, rtol=args.rtol, atol=args.atol, loss=args.loss, smooth=args.smooth,
        coarse_to_fine=args.coarse_to_fine, search=_off(args.no_search), uniform_check=_off(args.no_uniform_check),
        repair=_off(args.no_repair), noise_level=args.noise_level, devices=devices, ibl=args.ibl,
        pixel_ibl_settings=pixel_ibl_settings, occlusion=args.occlusion,
        occlusion_settings=OcclusionSettings(bounce=args.bounce or OcclusionSettings.bounce),
        continuation=None if args.continuation is None else continuation,
        pixel_samples=pixel_samples,
        cg_rtol=args.cg_rtol, noise_rtol=args.noise_rtol, loss_scale=args.loss_scale,
        uncertainty_radius=args.uncertainty_radius,
        unconstrained_sigma=args.unconstrained_sigma, model=model_changes(args.model) or None, quality=args.quality)
    # an option left out is the --quality rung's, else its default
    try:  # checked as `pbrfit.fit` checks them, worded with the flags
        return FitOptions(**{k: v for k, v in options.items() if v is not None or k in _NONE_IS_A_VALUE},
                          names=OptionNames(flags=True, held_by=held_by))
    except ValueError as e:
        raise CaptureError(str(e)) from None


#: The options whose value None means something (not "the default"): the map size from the
#: views, every map not held, one device, the capture's model.
_NONE_IS_A_VALUE = ("resolution", "fit", "devices", "model")


def fit_devices(text: str) -> Optional[list]:
    """--devices: "auto" (every local device of an accelerator backend; on the CPU one device,
    as several host devices share the same cores) or a count from 1 to the devices JAX sees;
    None for one device."""
    available = jax.local_devices()
    if text == "auto":
        return available if jax.default_backend() != "cpu" and len(available) > 1 else None
    count = int(text) if text.isascii() and text.isdigit() else 0
    if not 1 <= count <= len(available):
        raise CaptureError(f"--devices: expected auto or 1 to {len(available)} (the devices JAX sees), got {text}")
    return available[:count] if count > 1 else None


def _off(flag: bool) -> Optional[bool]:
    """A stage a ``--no-...`` flag turns off: False where given, else left to the rung."""
    return False if flag else None


def _continuation(text: str) -> tuple:
    """--continuation: 'none' or comma-separated finite weights >= 0."""
    if text.strip().lower() in ("none", "off", ""):
        return ()
    try:
        weights = tuple(float(w) for w in text.split(","))
    except ValueError:
        weights = ()

    if not weights or not all(math.isfinite(w) and 0 <= w <= FLOAT32_MAX for w in weights):
        raise CaptureError(f"--continuation: expected 'none' or comma-separated weights >= 0 within float32, "
                           f"got {text!r}")
    return weights


def fit_summary(result, errors) -> str:
    r = result.report
    h, w = r["resolution"]
    extra = f", per-pixel IBL {r['ibl']['seconds']:.1f} s" if r.get("ibl", {}).get("mode") == "per_pixel" else ""
    parts = [f"fit {h}x{w} maps with {r['solver']}: {r['steps']} steps, loss {r['final_loss']:.3e}",
             f"{r['wall_time']:.1f} s ({compile_summary(r['times'])}{extra})"]
    n, foot = r.get("pixel_samples", 1), r.get("footprint")
    if foot is not None and "skipped" in foot:  # auto, on a capture too large to try the samples
        parts[0] += ", pixel centres (auto: the footprint's samples skipped, too many pixels)"
    elif foot is not None and "energies" in foot:  # auto, both: which explained the images, and by how much
        other = next(k for k in foot["energies"] if int(k) != foot["selected"])
        where = "pixel centres" if n == 1 else f"{n}x{n} samples per pixel"
        parts[0] += (f", {where} (auto: data loss {foot['energies'][str(foot['selected'])]:.3e} against "
                     f"{foot['energies'][other]:.3e} {'at centres' if other == '1' else f'with {other}x{other}'})")
    elif n > 1:
        parts[0] += f", {n}x{n} samples per pixel"
    choice = (r.get("ibl") or {}).get("choice")
    if choice is not None and "skipped" in choice:  # auto: called for, but too many pixels to integrate unasked
        parts[0] += f", split-sum IBL (auto: its residuals call for per-pixel integrals; {choice['skipped']})"
    if choice is not None and choice["tried"]:  # auto: the split sum's residuals showed light it cannot model
        parts[0] += (f", {r['ibl']['mode'].replace('_', '-')} IBL (auto: residual sigma "
                     f"{choice['residual_sigma']['per_pixel']:.3g} per-pixel against "
                     f"{choice['residual_sigma']['split_sum']:.3g} split-sum)")
    if r.get("unseen_texels"):  # no view sees them: left at the prior, σ +inf (coverage.exr 0)
        parts[0] += f", {r['unseen_texels']} of {h * w} texels unseen (not fitted: coverage 0)"
    uniform = [f"{name} {r['uniform_check'][name]['value']:.4g}" for name in uniform_channels(r)]
    if uniform:  # the uniform check found no support for these maps in the images
        parts[0] += ", one value for " + " and ".join(uniform) + " (uniform check)"
    held = (r.get("unconstrained") or {}).get("texels", 0)
    if held:  # roughness the images do not constrain: at the prior, not the noise's value
        parts[0] += (f", roughness held at 0.5 on {held} texel{'' if held == 1 else 's'} the images do not "
                     f"constrain (σ > {r['unconstrained']['threshold']:g})")
    level = r.get("noise_level") or {}
    kept = [p for p in (r.get("repair") or {}).get("passes", []) if p.get("kept")]
    if kept:  # texels a solve had left in a wrong basin, started again (estimated: in the first fit)
        clusters = sum(p["clusters_kept"] for p in kept)
        whose = "the first fit's " if level.get("mode") == "estimated" else ""
        parts[0] += (f", {whose}repair re-solved {sum(p['texels_kept'] for p in kept)} texels in {clusters} "
                     f"cluster{'' if clusters == 1 else 's'} (loss {kept[0]['energy_before']:.3e}"
                     f" -> {kept[-1]['energy_after']:.3e})")
    if level.get("mode") == "estimated":  # two fits: the second weighted by the first's noise level
        parts[0] += (f", weighted by the estimated noise level ({min(level['sigma']):.2g} to "
                     f"{max(level['sigma']):.2g}; first fit loss {level['first_fit']['final_loss']:.3e})")
    if errors:
        parts.append("RMSE " + ", ".join(f"{k} {v:.4f}" for k, v in errors.items()))
    return "; ".join(parts)


def describe(info: dict) -> str:
    """The progress line's text for one of a fit's progress entries: a step ``level 0 (64x64)
    step  12/40  loss 1.2345e-03`` (of at most 40 in this solve; the step alone where a solver
    gives no budget), or the stage that begins (``level 0 (64x64) search``), with
    where it is (the automatic footprint's finish, the repair's pass, the weighted fit, the
    uniform check's channel) between them."""
    if info.get("stage") == "ibl":  # the per-pixel integrals before the solve
        return f"per-pixel IBL {info['done']:,} / {info['total']:,} pixels"
    h, w = info["resolution"]
    n = info.get("footprint")  # the auto footprint's two finishes: centres, then samples
    where = "" if n is None else ("  pixel centres" if n == 1 else f"  {n}x{n} samples")
    if "repair" in info:
        where += f"  repair {info['repair']}"
    if info.get("weighted"):
        where += "  weighted"
    if "check" in info:
        where += f"  uniform {info['check']}?"
    if "loss" not in info:
        return f"level {info['level']} ({h}x{w}){where}  {info['stage']}"
    of = f"/{info['budget']}" if info.get("budget") is not None else ""
    return f"level {info['level']} ({h}x{w}){where} step {info['step']:3d}{of}  loss {info['loss']:.4e}"


class FitProgress:
    """A live line (rich) with where the fit is (`describe`: level, stage or step and loss) and the
    elapsed time; also keeps the loss history (the steps' entries)."""

    def __init__(self, enabled: bool):
        self.history = []
        self._start = time.perf_counter()
        self._clock = time.perf_counter
        self._live = None
        if enabled and sys.stderr.isatty():
            self._live = Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                                  transient=True)
            self._task = self._live.add_task("fitting")
            self._live.start()

    def __call__(self, info: dict) -> None:
        if "loss" in info:
            self.history.append(dict(info, time=self._clock() - self._start))
        if self._live is not None:
            self._live.update(self._task, description=describe(info))

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
        write_normal=normals, truth=None if truth is None else truth_at(truth, result.material.resolution),
    )
    return result, errors

