"""The `pbrfit` command: argument parsing, progress and exit codes.

Each subcommand is a thin layer over the Python API. Bad input ends the command with one line
on stderr, ``pbrfit: error: <what and where>``, and exit status 2; nothing is half written.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import warnings
from typing import Optional, Sequence

from .errors import CaptureError

__all__ = ["main"]

EXIT_OK = 0
EXIT_FAILED = 1  # the command ran but its check failed (e.g. a gradient check)
EXIT_USAGE = 2  # bad input: a capture, a file, an option


# --- check-grads -----------------------------------------------------------------------------
def _add_check_grads(sub) -> None:
    p = sub.add_parser("check-grads", help="gradient checks of every BRDF term (autodiff vs finite differences)")
    p.add_argument("--quiet", action="store_true", help="print only failures and the summary line")


def _cmd_check_grads(args) -> int:
    from .gradcheck import print_report, run_checks

    results = run_checks()
    ok = print_report(results, quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED


# --- demo ------------------------------------------------------------------------------------
def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="synthesize a capture on the embedded defaults and fit it")
    p.add_argument("--out", default="pbrfit-demo", help="output folder (default ./pbrfit-demo)")
    p.add_argument("--quiet", action="store_true", help="print only errors")


def _cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(out=args.out, quiet=args.quiet)


# --- render ----------------------------------------------------------------------------------
def _add_render(sub) -> None:
    p = sub.add_parser(
        "render",
        help="render every view of a capture with a material folder (fit-output layout) into a new capture",
    )
    p.add_argument("capture", help="capture folder or capture.json")
    p.add_argument("--material", required=True, help="material folder (base_color.exr, metallic.exr, ...)")
    p.add_argument("--out", required=True, help="output capture folder (written whole or not at all; replaces only an earlier capture folder)")
    p.add_argument("--supersample", type=int, default=1, metavar="K",
                   help="each pixel the mean of K x K samples over its area, as a supersampled render or a camera "
                        "gives it (the footprint `fit --pixel-samples K` models, for K up to 4), its alpha 1 where "
                        f"every sample hits the mesh; time grows as K^2; default 1: pixel centres (at most "
                        f"{MAX_SUPERSAMPLE})")
    p.add_argument("--environment", help="relight with this equirect HDR instead of the capture's (the capture's intensity and rotation_deg apply to it)")
    p.add_argument("--lights", help="relight with these global lights: a JSON file, or inline JSON, holding a list of lights "
                        "(KHR_lights_punctual units)")
    p.add_argument("--cache", help="G-buffer cache folder (default $PBRFIT_CACHE, else $XDG_CACHE_HOME/pbrfit, else ~/.cache/pbrfit)")
    p.add_argument("--no-cache", action="store_true", help="do not read or write the G-buffer cache")
    p.add_argument("--quiet", action="store_true", help="print only errors")


def _cache_dir(args):
    """The G-buffer (and XLA) cache folder of a command, or None; a path that is not a folder
    is refused."""
    from pathlib import Path

    from .views import default_cache_dir

    if getattr(args, "no_cache", False):
        return None
    folder = Path(args.cache) if getattr(args, "cache", None) else default_cache_dir()
    if folder.exists() and not folder.is_dir():
        where = "--cache" if getattr(args, "cache", None) else "cache folder ($PBRFIT_CACHE, $XDG_CACHE_HOME/pbrfit or ~/.cache/pbrfit)"
        raise CaptureError(f"{where} {folder}: exists and is not a folder")
    return folder


def _cmd_render(args) -> int:
    import time

    import numpy as np

    from .atomic import check_not_inside, check_output_dir
    from .gltf_export import needs_texture_coordinates
    from .material_files import read_material
    from .mesh import check_uv_layout
    from .scene import load_capture
    from .views import apply_overrides, load_lights_override, render_capture, write_rendered_capture

    start = time.perf_counter()
    if not 1 <= args.supersample <= MAX_SUPERSAMPLE:
        raise CaptureError(f"--supersample: must be from 1 to {MAX_SUPERSAMPLE}, got {args.supersample}")
    check_output_dir(args.out, "capture")
    capture = load_capture(args.capture, require_uv=False)
    check_not_inside(capture.root, args.out, "capture being rendered")
    check_not_inside(args.material, args.out, "material being rendered")
    material = read_material(args.material)
    if needs_texture_coordinates(material):  # not a uniform one (1 x 1 maps, as `fit --maps none` writes)
        check_uv_layout(capture.mesh, f"{capture.json_path}: mesh")
    lights_json = load_lights_override(args.lights) if args.lights else None
    capture = apply_overrides(capture, args.environment, lights_json)
    emits = material.emissive is not None and np.any(np.asarray(material.emissive) > 0)
    if capture.environment is None and not emits and not any(
            float(light.intensity) * float(np.max(np.asarray(light.color))) > 0.0
            for frame in capture.frames for light in frame.lights):
        where = "--lights" if lights_json is not None else str(capture.json_path)
        raise CaptureError(f"{where}: no light: no environment, every light is off and the material emits none, "
                           "so every render would be black (give --lights or --environment)")
    renders = render_capture(capture, material, cache_dir=_cache_dir(args), supersample=args.supersample)
    write_rendered_capture(capture, renders, args.out, args.environment, lights_json)
    if not args.quiet:
        print(f"rendered {len(renders)} views to {args.out} in {time.perf_counter() - start:.1f} s")
    return EXIT_OK


# --- synth -----------------------------------------------------------------------------------
def _add_synth(sub) -> None:
    from data_synth.noise import NOISE_MODELS
    from data_synth.presets import IMAGE_FORMATS, describe_presets, preset_names

    p = sub.add_parser(
        "synth",
        help="write a synthetic capture with ground-truth maps (data_synth presets)",
        description="Render a procedural scene and write it as a capture folder with truth/ maps.",
        epilog="presets:\n" + describe_presets(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("preset", choices=preset_names(), metavar="PRESET", help="one of: " + ", ".join(preset_names()))
    p.add_argument("--out", required=True, help="capture folder to write (replaced if it holds a capture)")
    p.add_argument("--seed", type=int, default=0, help="every random choice follows from it (default 0)")
    p.add_argument("--size", type=int, help="image width and height in pixels (default: the preset's)")
    p.add_argument("--views", type=int, help="number of cameras (default: the preset's)")
    p.add_argument("--noise", type=float, help="noise std at a display value of 1 (0 = none)")
    p.add_argument("--noise-model", choices=NOISE_MODELS, help="gaussian (additive), relative (std proportional to the value) or poisson_gaussian")
    p.add_argument("--supersample", type=int, help="render k x k samples per pixel and box-filter down")
    p.add_argument("--texture-size", type=int, help="ground-truth map resolution (default: the preset's; spheres-grid rounds it down to a multiple of 5, one tile per sphere)")
    p.add_argument("--format", choices=sorted(IMAGE_FORMATS), help="exr (linear float), png16 or png8 (sRGB)")
    p.add_argument("--mesh", help="mesh-env: a mesh file with texture coordinates")
    p.add_argument("--shape", choices=("torus", "box", "sphere"), help="mesh-env: built-in shape")
    p.add_argument("--ibl", choices=("split_sum", "monte_carlo"), default="split_sum",
                   help="environment light: split_sum (default; pbrfit's renderer) or monte_carlo (the reference "
                        "integrator: ground truth, as a path tracer renders it)")
    p.add_argument("--ibl-samples", type=int, help="monte_carlo: sample steps per pixel sample (default 1024)")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")


def _cmd_synth(args) -> int:
    import math
    from pathlib import Path

    from data_synth.presets import make_scene
    from data_synth.writer import synthesize

    from .atomic import check_output_dir

    bounds = (("size", 1, MAX_SIZE), ("views", 1, MAX_VIEWS), ("supersample", 1, MAX_SUPERSAMPLE),
              ("texture_size", 1, MAX_SIZE), ("ibl_samples", 1, MAX_IBL_SAMPLES), ("seed", 0, None))
    for name, low, high in bounds:
        value = getattr(args, name)
        if value is not None and value < low:
            raise CaptureError(f"--{name.replace('_', '-')}: must be at least {low}, got {value}")
        if value is not None and high is not None and value > high:
            raise CaptureError(f"--{name.replace('_', '-')}: must be at most {high}, got {value}")
    if args.noise is not None and not (math.isfinite(args.noise) and args.noise >= 0):
        raise CaptureError(f"--noise: must be a finite number >= 0, got {args.noise}")
    if args.noise is not None and args.noise > MAX_NOISE:
        raise CaptureError(f"--noise: must be at most {MAX_NOISE:g} (a std {MAX_NOISE:g} times display white), "
                           f"got {args.noise:g}")
    if args.ibl_samples is not None and args.ibl != "monte_carlo":
        raise CaptureError("--ibl-samples: only --ibl monte_carlo uses it")
    if args.mesh is not None and args.shape is not None:
        raise CaptureError("--shape: --mesh gives the mesh already; give one of the two")
    out = Path(args.out)
    check_output_dir(out, "capture")
    overrides = dict(
        size=args.size, views=args.views, noise=args.noise, noise_model=args.noise_model,
        supersample=args.supersample, texture_size=args.texture_size, image_format=args.format,
        mesh=args.mesh, shape=args.shape,
    )  # fmt: skip
    scene = make_scene(args.preset, args.seed, **overrides)
    if args.ibl == "monte_carlo":
        if scene.model.ibl is None:
            raise CaptureError(f"--ibl monte_carlo: preset {args.preset} has no environment light to integrate")
        samples = 1024 if args.ibl_samples is None else args.ibl_samples
        scene = scene.replace(model=scene.model.replace(ibl="monte_carlo"), mc_samples=samples)
    result = synthesize(scene, out)
    if not args.quiet:
        h, w = scene.truth.shape
        print(
            f"synth {scene.name} (seed {scene.seed}): {scene.num_views} views {scene.width}x{scene.height} "
            f"{scene.image_format}, maps {w}x{h} -> {out} ({result.seconds:.1f} s)"
        )
    return EXIT_OK


# --- fit -------------------------------------------------------------------------------------


def _add_fit(sub) -> None:
    from .fit_options import IBL_MODES, MATERIAL_MAPS
    from .fit_pass import MAX_STEPS
    from .runner import DEFAULT_SOLVER, SOLVERS
    from .noise import NOISE_LEVELS
    from .observations import MAX_PIXEL_SAMPLES
    from .pixel_ibl import PixelIBLSettings
    from .solvers import LOSSES

    p = sub.add_parser("fit", help="fit base color, metallic and roughness maps to a capture")
    p.add_argument("capture", help="capture folder, capture.json or NeRF-style transforms.json")
    p.add_argument("--out", required=True, help="output folder (written whole or not at all; replaces only an earlier fit output)")
    p.add_argument("--resolution", type=int, help="map size N (N x N); default from the views' texel coverage")
    p.add_argument("--maps", choices=("texture", "none"), default="texture",
                   help="'none' fits one uniform material (five numbers)")
    p.add_argument("--fit",
                   help="comma-separated maps to fit, some of base_color, metallic, roughness, normal "
                        "(a tangent-space normal map, written as normal.png); default: the three maps "
                        "not held by --base-color, --metallic, --roughness or --*-from; a map neither fitted nor "
                        "held stays at the prior (base color 0.5 grey, metallic 0, roughness 0.5; report.json's "
                        "\"held\" says what each map was held at)")
    p.add_argument("--base-color", help="hold base color fixed at R,G,B (linear)")
    p.add_argument("--metallic", type=float, help="hold metallic fixed at this value")
    p.add_argument("--roughness", type=float, help="hold roughness fixed at this value (perceptual)")
    for name in MATERIAL_MAPS:
        flag = name.replace("_", "-")
        p.add_argument(f"--{flag}-from", metavar="DIR", help=f"hold {name} fixed at the map in a material folder")
    p.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER, help=f"default {DEFAULT_SOLVER}")
    p.add_argument("--max-steps", type=int, help=f"solver steps at the final resolution (default {MAX_STEPS}); the repair's and the "
                        "uniform check's re-fits come on top")
    p.add_argument("--rtol", type=float, default=1e-6,
                   help="relative stopping tolerance: the structured solver stops at an accepted step that lowers the "
                        "loss by less than this fraction of it; the optimistix solvers' rtol (default 1e-6)")
    p.add_argument("--atol", type=float, default=1e-5,
                   help="absolute stopping tolerance: the structured solver also stops at an accepted step that moves "
                        "no parameter by more than this; the optimistix solvers' atol (default 1e-5)")
    p.add_argument("--cg-rtol", type=float, default=None, metavar="TOL",
                   help="structured solver: relative tolerance of each step's conjugate gradients, in (0, 1) "
                        "(default 1e-3; 1e-2 solves about a quarter faster, see the README)")
    p.add_argument("--loss", choices=LOSSES, default="l2", help="robust loss (default l2: off)")
    p.add_argument("--smooth", type=float, default=0.0, help="weight of the smoothness prior (default 0: off)")
    p.add_argument("--coarse-to-fine", action="store_true", help="solve a uniform material and coarser maps first")
    p.add_argument("--ibl", choices=IBL_MODES, default=IBL_MODES[0],
                   help="environment light: split_sum (default; the renderer's tables) or per_pixel "
                        "(each pixel's integrals by Monte Carlo before the solve: no split-sum error, slower setup)")
    p.add_argument("--ibl-samples", type=int,
                   help=f"per_pixel: sample steps per pixel (default {PixelIBLSettings.samples})")
    p.add_argument("--ibl-levels", type=int,
                   help=f"per_pixel: roughness levels tabulated (default {PixelIBLSettings.levels})")
    p.add_argument("--pixel-samples", default="auto", metavar="{auto,N}",
                   help=f"shade N x N samples per pixel (N from 1 to {MAX_PIXEL_SAMPLES}) and fit their mean: the pixel "
                        "footprint of an antialiased or supersampled capture (1: pixel centres; cost grows as N^2). Default auto: pixel centres for "
                        "linear HDR images; for sRGB or tone-mapped ones, fit both 2 x 2 samples and centres and keep "
                        "the better match")
    p.add_argument("--no-search", action="store_true",
                   help="skip the per-texel re-search of metallic and roughness midway through the solve")
    p.add_argument("--no-repair", action="store_true",
                   help="skip the repair after the solve (by default well-seen texels whose pixels fit worse than "
                        "the noise explains, then those out of line with their neighbours, are started again from "
                        "their nearest well-fitted neighbour, re-searched and re-solved with their neighbours, each "
                        "cluster kept where its pixels fit better and the loss falls; report.json's repair says what "
                        "each pass did)")
    p.add_argument("--uncertainty-radius", type=int, default=None, metavar="R",
                   help="uncertainty.exr: each texel's standard error with the (2R+1) x (2R+1) texels around it "
                        "free as well (0, 1 or 2; default 1; 0: its own block of the normal matrix, the neighbours "
                        "held, about 10-15%% too small on the peer scene; 2: within 0.1%% of the whole matrix's on a "
                        "small map, about 4 times the cost; see the README)")
    p.add_argument("--noise-level", choices=NOISE_LEVELS, default="uniform",
                   help="uniform (default): every residual weighs alike (plain least squares, the likeliest fit "
                        "when the noise does not depend on the value); estimated: the noise level as a function "
                        "of the value is measured from a first fit's residuals, and a second fit from its maps "
                        "weighs each residual by the inverse of the level at its value (for shot noise, or noise "
                        "proportional to the signal; 1.1 to 1.5 times the time; report.json's noise_level gives the "
                        "level function)")
    p.add_argument("--no-uniform-check", action="store_true",
                   help="keep metallic and roughness as maps even where the images support only one value for "
                        "them (by default a map the images cannot tell apart from one value, by Akaike's criterion, "
                        "becomes that value; report.json's uniform_check says what each test found)")
    p.add_argument("--continuation", metavar="W[,W...]",
                   help="weights of the smoothness prior over the first steps, relative to the data's curvature, "
                        f"released before the end (default {_default_continuation()}; 'none' turns it off)")
    p.add_argument("--devices", type=int,
                   help="split the pixels over this many JAX devices (default: one device)")
    p.add_argument("--cache", help="G-buffer and per-pixel IBL cache folder (default $PBRFIT_CACHE, else $XDG_CACHE_HOME/pbrfit, else ~/.cache/pbrfit)")
    p.add_argument("--no-cache", action="store_true", help="do not read or write the cache")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary line; warnings and errors still print")


def _fit_options(args) -> dict:
    """Keyword arguments of `pbrfit.fit.fit` from the command line (errors name the option)."""
    from .fit_options import LOSS_SCALE, MATERIAL_MAPS, OptionNames, check_options, fit_arguments
    from .fit_pass import COARSE_STEPS
    from .runner import DEFAULT_SOLVER
    from .material_files import read_map
    from .observations import MAX_PIXEL_SAMPLES
    from .pixel_ibl import MIN_LEVELS, MIN_SAMPLES, PixelIBLSettings
    from .solvers import CG_RTOL
    from .uncertainty import WINDOW_RADIUS

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
            fixed[name], held_by[name] = read_map(folder, name), f"--{flag}-from"
    continuation = _continuation(_default_continuation() if args.continuation is None else args.continuation)
    # a flag a mode does not read is refused even at its default value (check_options, which sees
    # values only, refuses values other than the default)
    for flag, given in (("--cg-rtol", args.cg_rtol is not None), ("--continuation", args.continuation is not None
                                                                   and bool(continuation))):
        if given and args.solver != DEFAULT_SOLVER:
            raise CaptureError(f"{flag}: only the {DEFAULT_SOLVER} solver uses it, not --solver {args.solver}")
        if given and flag == "--continuation" and args.maps == "none":
            raise CaptureError(f"{flag}: --maps none fits one uniform material (1 x 1 maps)")
    names = OptionNames(flags=True, held_by=held_by)
    try:  # the checks `pbrfit.fit` makes, worded with the flags
        free, fixed = fit_arguments(args.fit, fixed, names)
        check_options(resolution=args.resolution, maps=args.maps, solver=args.solver, max_steps=args.max_steps,
                      coarse_steps=COARSE_STEPS, rtol=args.rtol, atol=args.atol,
                      cg_rtol=CG_RTOL if args.cg_rtol is None else args.cg_rtol, loss_scale=LOSS_SCALE,
                      smooth=args.smooth, coarse_to_fine=args.coarse_to_fine,
                      continuation=continuation if args.continuation is not None else None,
                      uncertainty_radius=WINDOW_RADIUS if args.uncertainty_radius is None else args.uncertainty_radius,
                      names=names)
    except ValueError as e:
        raise CaptureError(str(e)) from None
    for name in ("ibl_samples", "ibl_levels"):
        if getattr(args, name) is not None and args.ibl != "per_pixel":
            raise CaptureError(f"--{name.replace('_', '-')}: only --ibl per_pixel uses it")
    pixel_samples = args.pixel_samples
    if pixel_samples != "auto":
        if not (pixel_samples.isascii() and pixel_samples.isdigit() and 1 <= int(pixel_samples) <= MAX_PIXEL_SAMPLES):
            raise CaptureError(f"--pixel-samples: expected auto or 1 to {MAX_PIXEL_SAMPLES}, got {args.pixel_samples}")
        pixel_samples = int(pixel_samples)
    if "normal" in free and args.ibl == "per_pixel":
        raise CaptureError("--ibl per_pixel: fitted normals need --ibl split_sum (per-pixel integrals hold the normals fixed)")
    for flag, value, least, most in (("--ibl-levels", args.ibl_levels, MIN_LEVELS, MAX_IBL_LEVELS),
                                     ("--ibl-samples", args.ibl_samples, MIN_SAMPLES, MAX_IBL_SAMPLES)):
        if value is not None and not least <= value <= most:
            raise CaptureError(f"{flag}: must be between {least} and {most}, got {value}")
    pixel_ibl_settings = PixelIBLSettings(
        levels=PixelIBLSettings.levels if args.ibl_levels is None else args.ibl_levels,
        samples=PixelIBLSettings.samples if args.ibl_samples is None else args.ibl_samples)
    devices = None
    if args.devices is not None:
        import jax

        available = jax.devices()
        if not 1 <= args.devices <= len(available):
            raise CaptureError(f"--devices: expected 1 to {len(available)} (the devices JAX sees), got {args.devices}")
        devices = available[: args.devices] if args.devices > 1 else None
    return dict(
        fit=free, fixed=fixed, maps=args.maps, resolution=args.resolution, solver=args.solver,
        max_steps=args.max_steps, rtol=args.rtol, atol=args.atol, loss=args.loss, smooth=args.smooth,
        coarse_to_fine=args.coarse_to_fine, search=not args.no_search, uniform_check=not args.no_uniform_check,
        repair=not args.no_repair, noise_level=args.noise_level, devices=devices, ibl=args.ibl,
        pixel_ibl_settings=pixel_ibl_settings, continuation=continuation, pixel_samples=pixel_samples,
        **({} if args.cg_rtol is None else dict(cg_rtol=args.cg_rtol)),
        **({} if args.uncertainty_radius is None else dict(uncertainty_radius=args.uncertainty_radius)),
    )


def _continuation(text: str) -> tuple:
    """--continuation: 'none' or comma-separated finite weights >= 0."""
    import math

    if text.strip().lower() in ("none", "off", ""):
        return ()
    try:
        weights = tuple(float(w) for w in text.split(","))
    except ValueError:
        weights = ()
    from .fit_options import FLOAT32_MAX

    if not weights or not all(math.isfinite(w) and 0 <= w <= FLOAT32_MAX for w in weights):
        raise CaptureError(f"--continuation: expected 'none' or comma-separated weights >= 0 within float32, "
                           f"got {text!r}")
    return weights


class _Progress:
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


def _loss_history(steps: list, report: dict) -> list:
    """The convergence plot's (step, loss) points: every step reported, but of the automatic
    footprint's two finishes (entries tagged "footprint") only the kept one's, of the repair's
    passes (tagged "repair", numbered from 1) only the kept ones', and of the uniform check's
    re-fits (tagged "check") only those of a channel made uniform. With an estimated noise level
    only the weighted fit's steps (tagged "weighted"): its loss is of the weighted residuals, on
    another scale than the first fit's."""
    from .selection import uniform_channels

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


def run_fit(capture, out, options: dict, cache_dir=None, quiet: bool = False):
    """Fit `capture`, add truth errors to the report when `truth/` exists, write `out`; return
    (result, per-map RMSE or None)."""
    import numpy as np

    from .fit import fit, map_rmse
    from .material_files import read_material
    from .outputs import write_fit_output

    truth = None
    if capture.truth_dir is not None:  # read first: only evaluation uses it, so a bad one is skipped
        try:
            truth = read_material(capture.truth_dir)
        except CaptureError as err:
            print(f"pbrfit: warning: {err}; truth/ ignored (no truth_rmse)", file=sys.stderr)
    progress = _Progress(not quiet)
    try:
        result = fit(capture, cache_dir=cache_dir, progress=progress, **options)
    finally:
        progress.close()
    errors = None
    if truth is not None:
        errors = map_rmse(truth, result)
        result.report["truth_rmse"] = errors
    history = _loss_history(progress.history, result.report)
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


def _summary(result, errors) -> str:
    from .runner import compile_summary
    from .selection import uniform_channels

    r = result.report
    h, w = r["resolution"]
    extra = f", per-pixel IBL {r['ibl']['seconds']:.1f} s" if r.get("ibl", {}).get("mode") == "per_pixel" else ""
    parts = [f"fit {h}x{w} maps with {r['solver']}: {r['steps']} steps, loss {r['final_loss']:.3e}",
             f"{r['wall_time']:.1f} s ({compile_summary(r['times'])}{extra})"]
    n, foot = r.get("pixel_samples", 1), r.get("footprint")
    if foot is not None and "skipped" in foot:  # auto, on a capture too large to try the samples
        parts[0] += ", pixel centres (auto: 2x2 samples skipped, too many pixels)"
    elif foot is not None:  # auto: which footprint explained the images, and by how much
        other = next(k for k in foot["energies"] if int(k) != foot["selected"])
        where = "pixel centres" if n == 1 else f"{n}x{n} samples per pixel"
        parts[0] += (f", {where} (auto: data loss {foot['energies'][str(foot['selected'])]:.3e} against "
                     f"{foot['energies'][other]:.3e} {'at centres' if other == '1' else f'with {other}x{other}'})")
    elif n > 1:
        parts[0] += f", {n}x{n} samples per pixel"
    uniform = [f"{name} {r['uniform_check'][name]['value']:.4g}" for name in uniform_channels(r)]
    if uniform:  # the uniform check found no support for these maps in the images
        parts[0] += ", one value for " + " and ".join(uniform) + " (uniform check)"
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


def _cmd_fit(args) -> int:
    from pathlib import Path

    from .fit_options import MATERIAL_MAPS
    from .atomic import check_not_inside, check_output_dir
    from .scene import load_capture

    options = _fit_options(args)
    out = Path(args.out)
    check_output_dir(out, "fit")
    capture = load_capture(args.capture, require_uv=options["maps"] == "texture" or "normal" in options["fit"])
    check_not_inside(capture.root, out, "capture being fitted")
    for name in MATERIAL_MAPS:
        folder = getattr(args, f"{name}_from")
        if folder is not None:
            check_not_inside(folder, out, f"{name} map of --{name.replace('_', '-')}-from")
        if name not in options["fit"] and name not in options["fixed"] and not args.quiet:
            print(f"pbrfit: note: {name} is neither fitted nor held (--fit, --{name.replace('_', '-')}): "
                  "it stays at the prior", file=sys.stderr)
    if args.ibl == "per_pixel" and capture.environment is None:
        print(f"pbrfit: warning: --ibl per_pixel: {capture.root} has no environment; nothing to integrate",
              file=sys.stderr)
    result, errors = run_fit(capture, out, options, _cache_dir(args), args.quiet)
    if not args.quiet:
        print(_summary(result, errors))
        print(f"wrote {out}")
    return EXIT_OK


_COMMANDS = {
    "check-grads": _cmd_check_grads,
    "demo": _cmd_demo,
    "render": _cmd_render,
    "synth": _cmd_synth,
    "fit": _cmd_fit,
}


def _enable_compilation_cache(args) -> None:
    """Keep XLA compilations on disk beside the G-buffer cache, so a second run of a command
    skips part of its compile time (off with --no-cache or PBRFIT_NO_COMPILE_CACHE=1). JAX keeps
    no program with a host callback, so the solver's loop, which reports each step, compiles on
    every run (a small fit: 5.6 s of compile waited for, then 2.9 s on the second run)."""
    if getattr(args, "no_cache", False) or os.environ.get("PBRFIT_NO_COMPILE_CACHE"):
        return
    import jax

    try:
        folder = _cache_dir(args)
    except CaptureError:  # not a folder: the commands that use the cache say so; the rest run uncached
        return
    try:
        jax.config.update("jax_compilation_cache_dir", str(os.path.join(folder, "xla")))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    except Exception:  # an older or newer JAX without these options: run uncached
        pass


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line, ``pbrfit: error: <option>: <problem>
    (see pbrfit fit --help)``, like every other error, and status 2."""

    def error(self, message: str):
        self.exit(EXIT_USAGE, f"pbrfit: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="pbrfit",
        description="Differentiable glTF PBR material fitting: recover base color, metallic and roughness maps.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_demo, _add_fit, _add_render, _add_synth, _add_check_grads):
        add(sub)
    return parser


def _default_continuation() -> str:
    from .fit_pass import CONTINUATION

    return ",".join(str(w) for w in CONTINUATION)


#: The largest image side (`synth --size`) and texture side (`--texture-size`) taken.
MAX_SIZE = 8192
#: The most cameras `synth --views` renders, and the largest `synth --supersample` and
#: `render --supersample` (memory and time grow as its square).
MAX_VIEWS = 1024
MAX_SUPERSAMPLE = 16
#: The largest `synth --noise` std, in display values (white is 1): far beyond any sensor, and
#: within what `fit` reads (larger noise writes images too bright for its float32 solve).
MAX_NOISE = 100.0
#: The most Monte Carlo sample steps (`--ibl-samples`) and tabulated roughness levels
#: (`--ibl-levels`) taken: far beyond any use, and within the int32 counters of the jitted loops
#: (`pbrfit.fit_options.MAX_SOLVER_STEPS` bounds `--max-steps`, `MAX_MAP_SIDE` `--resolution`).
MAX_IBL_SAMPLES = 1 << 20
MAX_IBL_LEVELS = 256
#: What to make smaller when a command runs out of memory.
_LESS = {"fit": "use a smaller --resolution (or fewer or smaller images)",
         "render": "use smaller or fewer images, a smaller material or a smaller --supersample",
         "synth": "use a smaller --size, --views, --supersample or --texture-size",
         "demo": "free some memory (the demo needs about 2 GB)"}


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread: unwinds like KeyboardInterrupt (outputs under a
    temporary name are removed on the way out)."""


def _stdout_closed() -> bool:
    """Whether stdout's reader has gone; if so, stdout is pointed at the null device, so that what
    is left in its buffer goes nowhere at exit instead of into a second error."""
    try:
        sys.stdout.flush()
        return False
    except BrokenPipeError:
        pass
    except (OSError, ValueError):
        return False
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    except (OSError, ValueError):  # stdout is no file descriptor
        pass
    return True


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line, like the errors: ``pbrfit: warning: <message>``."""
    print(f"pbrfit: warning: {str(message).splitlines()[0] if str(message) else category.__name__}",
          file=sys.stderr if file is None else file)


def _raise_terminated(signum, frame):
    raise _Terminated()


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the `pbrfit` console script; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:  # --help (0) or a usage error (2, one line already printed)
        return int(stop.code or 0)
    if args.command is None:
        print(f"pbrfit: error: expected a command, one of {', '.join(_COMMANDS)} (see pbrfit --help)", file=sys.stderr)
        return EXIT_USAGE
    # a `kill` (SIGTERM) unwinds like Ctrl-C, so that half-written outputs are removed
    try:
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
        installed = True
    except ValueError:  # not the main thread: signals stay as they are
        previous, installed = None, False
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            _enable_compilation_cache(args)
            status = _COMMANDS[args.command](args)
            sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's last flush
            return status
    except BrokenPipeError:
        if not _stdout_closed():  # another pipe (a child's) broke: a bug, with its traceback
            raise
        return 141  # 128 + SIGPIPE, as a shell reports a command whose reader left (`| head -1`)
    except CaptureError as err:
        print(f"pbrfit: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        # the system refused a file (a name too long, a full disk, no permission, a read-only
        # place): one line naming it; anything else is a bug and keeps its traceback
        from .atomic import REFUSED_ERRNOS

        if err.errno not in REFUSED_ERRNOS:
            raise
        where = f"{err.filename}: " if err.filename else ""
        print(f"pbrfit: error: {where}{err.strerror or err}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as err:
        # out of memory: numpy's MemoryError (its message names the size) or XLA's RESOURCE_EXHAUSTED;
        # anything else is a bug, and keeps its traceback
        if not (isinstance(err, MemoryError) or "RESOURCE_EXHAUSTED" in str(err)):
            raise
        from .io import _first_line

        hint = _LESS.get(args.command, "use smaller inputs")
        print(f"pbrfit: error: out of memory: {_first_line(str(err))}; {hint}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("pbrfit: interrupted", file=sys.stderr)
        return 130
    except _Terminated:
        print("pbrfit: terminated", file=sys.stderr)
        return 143
    finally:
        if installed:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
