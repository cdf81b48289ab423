"""`pbrfit synth`: a data_synth preset rendered and written as a capture folder with its
ground-truth maps (`data_synth.writer.synthesize`), every flag checked first."""

from __future__ import annotations

import math
from pathlib import Path

from data_synth.mitsuba_render import MAX_SPP, check_scene, load_mitsuba
from data_synth.presets import MIN_DEPTH, Scene, make_scene
from data_synth.writer import synthesize

from .parser import EXIT_OK, MAX_NOISE, MAX_SIZE, MAX_SUPERSAMPLE, MAX_VIEWS
from ..errors import CaptureError
from ..io.atomic import check_output_dir
from ..lighting.settings import MAX_SAMPLES

__all__ = ["run"]


def run(args) -> int:
    """`pbrfit synth` on its parsed arguments; returns the exit status."""
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
        samples = Scene.mc_samples if args.ibl_samples is None else args.ibl_samples
        scene = scene.replace(model=scene.model.replace(ibl="monte_carlo"), mc_samples=samples)
    if args.renderer == "mitsuba":
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
