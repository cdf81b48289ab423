"""The `pbrfit` command: argument parsing, progress and exit codes.

Each subcommand is a thin layer over the Python API. Bad input ends the command with one line
on stderr, ``pbrfit: error: <what and where>``, and exit status 2; nothing is half written.
"""

from __future__ import annotations

import argparse
import sys
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
    p.add_argument("--quiet", action="store_true")


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
    p.add_argument("--out", required=True, help="output capture folder (written whole or not at all)")
    p.add_argument("--environment", help="relight with this equirect HDR instead of the capture's")
    p.add_argument("--lights", help="relight with these global lights: a JSON list (KHR_lights_punctual units)")
    p.add_argument("--cache", help="G-buffer cache folder (default $PBRFIT_CACHE or ~/.cache/pbrfit)")
    p.add_argument("--no-cache", action="store_true", help="do not read or write the G-buffer cache")
    p.add_argument("--quiet", action="store_true")


def _cache_dir(args):
    from .views import default_cache_dir

    if getattr(args, "no_cache", False):
        return None
    return args.cache if getattr(args, "cache", None) else default_cache_dir()


def _cmd_render(args) -> int:
    import time

    from .io import read_material
    from .scene import load_capture
    from .views import apply_overrides, load_lights_override, render_capture, write_rendered_capture

    start = time.perf_counter()
    capture = load_capture(args.capture)
    material = read_material(args.material)
    lights_json = load_lights_override(args.lights) if args.lights else None
    capture = apply_overrides(capture, args.environment, lights_json)
    renders = render_capture(capture, material, cache_dir=_cache_dir(args))
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
    p.add_argument("--size", type=int, help="image width and height in pixels")
    p.add_argument("--views", type=int, help="number of cameras")
    p.add_argument("--noise", type=float, help="noise std at a display value of 1 (0 = none)")
    p.add_argument("--noise-model", choices=NOISE_MODELS, help="gaussian or poisson_gaussian")
    p.add_argument("--supersample", type=int, help="render k x k samples per pixel and box-filter down")
    p.add_argument("--texture-size", type=int, help="ground-truth map resolution")
    p.add_argument("--format", choices=sorted(IMAGE_FORMATS), help="exr (linear float), png16 or png8 (sRGB)")
    p.add_argument("--mesh", help="mesh-env: a mesh file with texture coordinates")
    p.add_argument("--shape", choices=("torus", "box", "sphere"), help="mesh-env: built-in shape")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")


def _cmd_synth(args) -> int:
    from pathlib import Path

    from data_synth.presets import make_scene
    from data_synth.writer import synthesize

    for name, low in (("size", 1), ("views", 1), ("supersample", 1), ("texture_size", 1)):
        value = getattr(args, name)
        if value is not None and value < low:
            raise CaptureError(f"--{name.replace('_', '-')}: must be at least {low}, got {value}")
    if args.noise is not None and not args.noise >= 0:
        raise CaptureError(f"--noise: must be a number >= 0, got {args.noise}")
    out = Path(args.out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "capture.json").is_file())):
        raise CaptureError(f"--out {out}: exists and is not a capture folder; refusing to replace it")
    overrides = dict(
        size=args.size, views=args.views, noise=args.noise, noise_model=args.noise_model,
        supersample=args.supersample, texture_size=args.texture_size, image_format=args.format,
        mesh=args.mesh, shape=args.shape,
    )  # fmt: skip
    scene = make_scene(args.preset, args.seed, **overrides)
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
    pass


def _cmd_fit(args) -> int:
    raise NotImplementedError


_COMMANDS = {
    "check-grads": _cmd_check_grads,
    "demo": _cmd_demo,
    "render": _cmd_render,
    "synth": _cmd_synth,
    "fit": _cmd_fit,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pbrfit",
        description="Differentiable glTF PBR material fitting: recover base color, metallic and roughness maps.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_demo, _add_fit, _add_render, _add_synth, _add_check_grads):
        add(sub)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the `pbrfit` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        return _COMMANDS[args.command](args)
    except CaptureError as err:
        print(f"pbrfit: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("pbrfit: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
