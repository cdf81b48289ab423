"""The `pbrfit` command: argument parsing, progress and exit codes.

Each subcommand is a thin layer over the Python API. Bad input ends the command with one line
on stderr, ``pbrfit: error: <what and where>``, and exit status 2; nothing is half written.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from data_synth.mitsuba_render import MAX_SPP, NOISE_TARGET
from data_synth.noise import NOISE_MODELS
from data_synth.presets import (IMAGE_FORMATS, INTERREFLECTION_DEPTH, MIN_DEPTH, RENDERERS, describe_presets,
                                make_scene, preset_names)
from data_synth.writer import synthesize

from .demo import run_demo
from .fit import add_fit, fit_options, fit_summary, run_fit
from .model_flag import add_model_argument, model_changes
from ..checks import gradcheck
from ..errors import CaptureError
from ..fitting.options import MATERIAL_MAPS
from ..fitting.runner import enable_compilation_cache
from ..io.atomic import REFUSED_ERRNOS, check_not_inside, check_output_dir
from ..io.gltf_export import needs_texture_coordinates
from ..io.images import _first_line
from ..io.material_files import read_material
from ..lighting.pixel_ibl import MAX_SAMPLES
from ..render.output import write_rendered_capture
from ..render.views import (apply_overrides, capture_environment, default_cache_dir, environment_is_dark,
                            load_lights_override, model_for_capture, render_capture)
from ..scene.capture import load_capture
from ..scene.uv_layout import check_uv_layout

__all__ = ["main"]

EXIT_OK = 0
EXIT_FAILED = 1  # the command ran but its check failed (e.g. a gradient check)
EXIT_USAGE = 2  # bad input: a capture, a file, an option


# --- check-grads -----------------------------------------------------------------------------
def _add_check_grads(sub) -> None:
    p = sub.add_parser("check-grads", help="gradient checks of every BRDF term (autodiff vs finite differences)")
    p.add_argument("--quiet", action="store_true", help="print only failures and the summary line")


def _cmd_check_grads(args) -> int:
    results = gradcheck.run_checks()
    ok = gradcheck.print_report(results, quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED


# --- demo ------------------------------------------------------------------------------------
def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="synthesize a capture on the embedded defaults and fit it")
    p.add_argument("--out", default="pbrfit-demo", help="output folder (default ./pbrfit-demo)")
    p.add_argument("--quiet", action="store_true", help="print only errors")


def _cmd_demo(args) -> int:
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
    add_model_argument(p)
    p.add_argument("--cache", help="G-buffer cache folder (default $PBRFIT_CACHE, else $XDG_CACHE_HOME/pbrfit, else ~/.cache/pbrfit)")
    p.add_argument("--no-cache", action="store_true", help="do not read or write the G-buffer cache")
    p.add_argument("--quiet", action="store_true", help="print only errors")


def _cache_dir(args):
    """The G-buffer (and XLA) cache folder of a command, or None; a path that is not a folder
    is refused."""
    if getattr(args, "no_cache", False):
        return None
    folder = Path(args.cache) if getattr(args, "cache", None) else default_cache_dir()
    if folder.exists() and not folder.is_dir():
        where = "--cache" if getattr(args, "cache", None) else "cache folder ($PBRFIT_CACHE, $XDG_CACHE_HOME/pbrfit or ~/.cache/pbrfit)"
        raise CaptureError(f"{where} {folder}: exists and is not a folder")
    return folder


def _cmd_render(args) -> int:
    start = time.perf_counter()
    changes = model_changes(args.model)
    if not 1 <= args.supersample <= MAX_SUPERSAMPLE:
        raise CaptureError(f"--supersample: must be from 1 to {MAX_SUPERSAMPLE}, got {args.supersample}")
    check_output_dir(args.out, "capture")
    capture = load_capture(args.capture, require_uv=False)
    check_not_inside(capture.root, args.out, "capture being rendered")
    check_not_inside(args.material, args.out, "material being rendered")
    material = read_material(args.material)
    if needs_texture_coordinates(material):  # not a uniform one (1 x 1 maps, as `fit --maps none` writes)
        check_uv_layout(capture.mesh, f"{capture.json_path}: mesh")
    lights_json = load_lights_override(args.lights) if args.lights is not None else None
    capture = apply_overrides(capture, args.environment, lights_json)
    emits = material.emissive is not None and np.any(np.asarray(material.emissive) > 0)
    lit = emits or any(float(light.intensity) * float(np.max(np.asarray(light.color))) > 0.0
                       for frame in capture.frames for light in frame.lights)
    environment = None if lit else capture_environment(capture)  # read once: checked here, rendered below
    if not lit and environment_is_dark(capture, environment):
        where = "--lights" if lights_json is not None else str(capture.json_path)
        sky = "no environment" if capture.environment is None else f"the environment {capture.environment.file} is black"
        raise CaptureError(f"{where}: no light: {sky}, every light is off and the material emits none, "
                           "so every render would be black (give --lights or --environment)")
    model = model_for_capture(capture, material, **changes)
    if model.ibl is not None and capture.environment is None:
        raise CaptureError(f"--model: ibl={model.ibl} shades an environment light, and {capture.json_path} has none")
    renders = render_capture(capture, material, model, cache_dir=_cache_dir(args), supersample=args.supersample,
                             environment=environment)
    write_rendered_capture(capture, renders, args.out, args.environment, lights_json)
    if not args.quiet:
        print(f"rendered {len(renders)} views to {args.out} in {time.perf_counter() - start:.1f} s")
    return EXIT_OK


# --- synth -----------------------------------------------------------------------------------
def _add_synth(sub) -> None:
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
    p.add_argument("--renderer", choices=RENDERERS, default="pbrfit",
                   help="pbrfit (default) or mitsuba: Mitsuba 3's path tracer (pip install 'pbrfit[mitsuba]'), "
                        "with every shadow and, with --max-depth 3 or more, light between surfaces")
    p.add_argument("--max-depth", type=int, help=f"mitsuba: longest light path, {MIN_DEPTH} = direct light only "
                                                 f"(default: the preset's, {MIN_DEPTH} for a convex mesh, else "
                                                 f"{INTERREFLECTION_DEPTH})")
    p.add_argument("--spp", type=int, help="mitsuba: samples per pixel (default: enough for noise below "
                                           f"{100 * NOISE_TARGET:g}%%)")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")


def _cmd_synth(args) -> int:
    bounds = (("size", 1, MAX_SIZE), ("views", 1, MAX_VIEWS), ("supersample", 1, MAX_SUPERSAMPLE),
              ("texture_size", 1, MAX_SIZE), ("ibl_samples", 1, MAX_SAMPLES), ("seed", 0, None),
              ("max_depth", MIN_DEPTH, None), ("spp", 1, MAX_SPP))
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
    for name in ("max_depth", "spp"):
        if getattr(args, name) is not None and args.renderer != "mitsuba":
            raise CaptureError(f"--{name.replace('_', '-')}: only --renderer mitsuba uses it")
    if args.renderer == "mitsuba" and (args.ibl != "split_sum" or args.ibl_samples is not None):
        raise CaptureError("--ibl: --renderer mitsuba integrates the environment itself, by path tracing")
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
    if args.renderer == "mitsuba":
        from data_synth.mitsuba_render import check_scene, load_mitsuba

        load_mitsuba()  # the extra and its LLVM, before any work
        scene = scene.replace(renderer="mitsuba", spp=args.spp,
                              max_depth=scene.max_depth if args.max_depth is None else args.max_depth)
        check_scene(scene)
    result = synthesize(scene, out)
    if not args.quiet:
        h, w = scene.truth.shape
        how = "" if args.renderer != "mitsuba" else (f", mitsuba max_depth {scene.max_depth}, {result.renderer['spp']} "
                                                   f"spp, noise {result.renderer['noise']:.2%}")
        print(
            f"synth {scene.name} (seed {scene.seed}): {scene.num_views} views {scene.width}x{scene.height} "
            f"{scene.image_format}, maps {w}x{h}{how} -> {out} ({result.seconds:.1f} s)"
        )
    return EXIT_OK


# --- fit -------------------------------------------------------------------------------------


def _cmd_fit(args) -> int:
    options = fit_options(args)
    out = Path(args.out)
    check_output_dir(out, "fit")
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
    result, errors = run_fit(capture, out, options, _cache_dir(args), args.quiet)
    if not args.quiet:
        print(f"{fit_summary(result, errors)}; wrote {out}")
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

    try:
        folder = _cache_dir(args)
    except CaptureError:  # not a folder: the commands that use the cache say so; the rest run uncached
        return
    try:
        enable_compilation_cache(os.path.join(folder, "xla"))
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
    for add in (_add_demo, add_fit, _add_render, _add_synth, _add_check_grads):
        add(sub)
    return parser


#: The largest image side (`synth --size`) and texture side (`--texture-size`) taken.
MAX_SIZE = 8192
#: The most cameras `synth --views` renders, and the largest `synth --supersample` and
#: `render --supersample` (memory and time grow as its square).
MAX_VIEWS = 1024
MAX_SUPERSAMPLE = 16
#: The largest `synth --noise` std, in display values (white is 1): far beyond any sensor, and
#: within what `fit` reads (larger noise writes images too bright for its float32 solve).
MAX_NOISE = 100.0
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


def _printable(text: str) -> str:
    """``text`` with each control character escaped as Python writes it (a newline or a terminal
    escape in a file name becomes ``\\n``, ``\\x1b``): a message stays one line, and shows the name."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line, like the errors: ``pbrfit: warning: <message>`` (`_printable`)."""
    print(f"pbrfit: warning: {_printable(str(message).rstrip()) if str(message) else category.__name__}",
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
        print(f"pbrfit: error: {_printable(str(err))}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        # the system refused a file (a name too long, a full disk, no permission, a read-only
        # place): one line naming it; anything else is a bug and keeps its traceback

        if err.errno not in REFUSED_ERRNOS:
            raise
        where = f"{err.filename}: " if err.filename else ""
        print(f"pbrfit: error: {_printable(f'{where}{err.strerror or err}')}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as err:
        # out of memory: numpy's MemoryError (its message names the size) or XLA's RESOURCE_EXHAUSTED;
        # anything else is a bug, and keeps its traceback
        if not (isinstance(err, MemoryError) or "RESOURCE_EXHAUSTED" in str(err)):
            raise

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
