"""`pbrfit render`: every view of a capture rendered with a material folder, under the capture's
light or the one given (``--environment``, ``--lights``), written as a new capture."""

from __future__ import annotations

import time

import numpy as np

from .cache import cache_dir
from .model_flag import model_changes
from .parser import EXIT_OK, MAX_SUPERSAMPLE
from ..errors import CaptureError
from ..io.atomic import check_not_inside, check_output_dir
from ..io.gltf_export import needs_texture_coordinates
from ..io.material_files import read_material
from ..render.output import write_rendered_capture
from ..render.views import (apply_overrides, capture_environment, environment_is_dark, load_lights_override,
                            model_for_capture, render_capture)
from ..scene.capture import load_capture
from ..scene.uv_layout import check_uv_layout

__all__ = ["run"]


def run(args) -> int:
    """`pbrfit render` on its parsed arguments; returns the exit status."""
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
    if model.ibl in ("per_pixel", "monte_carlo"):  # a fit's integrals over its pixels, and the reference integrator
        raise CaptureError(f"--model: ibl={model.ibl} is not one render shades (per_pixel is a fit's, integrated over "
                           "its pixels; monte_carlo renders a capture through pbrfit synth --ibl monte_carlo): "
                           "give ibl=split_sum or ibl=none")
    if model.ibl is not None and capture.environment is None:
        raise CaptureError(f"--model: ibl={model.ibl} shades an environment light, and {capture.json_path} has none")
    renders = render_capture(capture, material, model, cache_dir=cache_dir(args), supersample=args.supersample,
                             environment=environment)
    write_rendered_capture(capture, renders, args.out, args.environment, lights_json)
    if not args.quiet:
        print(f"rendered {len(renders)} views to {args.out} in {time.perf_counter() - start:.1f} s")
    return EXIT_OK
