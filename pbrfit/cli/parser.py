"""The `pbrfit` command line as parsed: every command's flags (`build_parser`), the limits they
take and the exit statuses.

It imports no JAX, nor any module that does: the defaults and choices it shows come from the
rooms' modules that are free of it (`pbrfit.fitting.defaults`, `pbrfit.lighting.settings`,
`pbrfit.physics.model`, data_synth's presets), so that ``--help`` and a usage error answer at
once. A command's own module, which loads the fit's stack, is imported after parsing
(`pbrfit.cli.main`).
"""

from __future__ import annotations

import argparse
import math

from data_synth.mitsuba_render import NOISE_TARGET
from data_synth.noise import NOISE_MODELS
from data_synth.presets import IMAGE_FORMATS, INTERREFLECTION_DEPTH, MIN_DEPTH, RENDERERS, Scene, describe_presets, preset_names

from .model_flag import add_model_argument
from ..fitting.defaults import (ATOL, CG_RTOL, CONTINUATION, DEFAULT_SOLVER, IBL_MODES, LOSS_SCALE, LOSSES,
                                MATERIAL_MAPS, MAX_PIXEL_SAMPLES, MAX_STEPS, NOISE_LEVELS, NOISE_RTOL, QUALITY, RTOL,
                                SOLVERS)
from ..lighting.settings import BOUNCE_MODES, OCCLUSION_MODES, PixelIBLSettings

__all__ = ["build_parser", "add_fit", "default_continuation", "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "MAX_SIZE",
           "MAX_VIEWS", "MAX_SUPERSAMPLE", "MAX_NOISE"]

EXIT_OK = 0
EXIT_FAILED = 1  # the command ran but its check failed (e.g. a gradient check)
EXIT_USAGE = 2  # bad input: a capture, a file, an option

#: The largest image side (`synth --size`) and texture side (`--texture-size`) taken.
MAX_SIZE = 8192
#: The most cameras `synth --views` renders, and the largest `synth --supersample` and
#: `render --supersample` (memory and time grow as its square).
MAX_VIEWS = 1024
MAX_SUPERSAMPLE = 16
#: The largest `synth --noise` std, in display values (white is 1): far beyond any sensor, and
#: within what `fit` reads (larger noise writes images too bright for its float32 solve).
MAX_NOISE = 100.0


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


# --- check-grads -----------------------------------------------------------------------------
def _add_check_grads(sub) -> None:
    p = sub.add_parser("check-grads", help="gradient checks of every BRDF term (autodiff vs finite differences)")
    p.add_argument("--quiet", action="store_true", help="print only failures and the summary line")


# --- demo ------------------------------------------------------------------------------------
def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="synthesize a capture on the embedded defaults and fit it")
    p.add_argument("--out", default="pbrfit-demo", help="output folder (default ./pbrfit-demo)")
    p.add_argument("--quiet", action="store_true", help="print only errors")


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
    p.add_argument("--ibl-samples", type=int,
                   help=f"monte_carlo: sample steps per pixel sample (default {Scene.mc_samples})")
    p.add_argument("--renderer", choices=RENDERERS, default="pbrfit",
                   help="pbrfit (default) or mitsuba: Mitsuba 3's path tracer (pip install 'pbrfit[mitsuba]'), "
                        "with every shadow and, with --max-depth 3 or more, light between surfaces")
    p.add_argument("--max-depth", type=int, help=f"mitsuba: longest light path, {MIN_DEPTH} = direct light only "
                                                 f"(default: the preset's, {MIN_DEPTH} for a convex mesh, else "
                                                 f"{INTERREFLECTION_DEPTH})")
    p.add_argument("--spp", type=int, help="mitsuba: samples per pixel (default: enough for noise below "
                                           f"{100 * NOISE_TARGET:g}%%)")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")


# --- fit -------------------------------------------------------------------------------------
def add_fit(sub) -> None:
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
    p.add_argument("--quality", choices=tuple(QUALITY), default="default",
                   help="the speed ladder: draft previews in a fraction of the time (no search, repair, uniform check "
                        "or continuation; looser conjugate gradients and stopping; pixel centres), best solves to tighter tolerances; flags given "
                        "with it win (default: default; docs/options.md)")
    p.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER, help=f"default {DEFAULT_SOLVER}")
    p.add_argument("--max-steps", type=int, help=f"solver steps at the final resolution (default {MAX_STEPS}); the repair's and the "
                        "uniform check's re-fits come on top")
    p.add_argument("--rtol", type=float, default=None,
                   help="relative stopping tolerance: the structured solver stops at an accepted step that lowers the "
                        f"loss by less than this fraction of it; the optimistix solvers' rtol (default {RTOL:g})")
    p.add_argument("--atol", type=float, default=None,
                   help="absolute stopping tolerance: the structured solver also stops at an accepted step that moves "
                        f"no parameter by more than this; the optimistix solvers' atol (default {ATOL:g})")
    p.add_argument("--cg-rtol", type=float, default=None, metavar="TOL",
                   help="structured solver: relative tolerance of each step's conjugate gradients, in (0, 1) "
                        f"(default {CG_RTOL:g}; 1e-2 solves about a quarter faster, see docs/results.md)")
    p.add_argument("--noise-rtol", type=float, default=None, metavar="TOL",
                   help="structured solver: stop at an accepted step that gains less than TOL p s^2 / 2 (p free "
                        "channels, s^2 the residuals' variance): the maps then move by less than their noise "
                        f"(default {NOISE_RTOL:g}: {math.sqrt(NOISE_RTOL):g} standard error; 0: off)")
    p.add_argument("--loss", choices=LOSSES, default="l2", help="robust loss (default l2: off)")
    p.add_argument("--loss-scale", type=float, default=None, metavar="S",
                   help="the robust loss's scale, in image units: residuals past it count less "
                        f"(default {LOSS_SCALE:g}; huber and cauchy only)")
    p.add_argument("--smooth", type=float, default=0.0, help="weight of the smoothness prior (default 0: off)")
    p.add_argument("--coarse-to-fine", action="store_true", help="solve a uniform material and coarser maps first")
    p.add_argument("--ibl", choices=IBL_MODES, default=IBL_MODES[0],
                   help="environment light: split_sum (the renderer's tables), per_pixel (each pixel's integrals by "
                        "Monte Carlo before the solve: no split-sum error, slower setup) or auto (default: the split "
                        "sum, and per-pixel integrals too where its residuals show light it cannot model, as from a "
                        "path tracer or a camera; the better fit is kept)")
    p.add_argument("--ibl-samples", type=int,
                   help=f"per-pixel integrals: sample steps per pixel (default {PixelIBLSettings.samples})")
    p.add_argument("--ibl-levels", type=int,
                   help=f"per-pixel integrals: roughness levels tabulated (default {PixelIBLSettings.levels})")
    p.add_argument("--occlusion", choices=OCCLUSION_MODES,
                   help="whether the mesh shadows the environment light on itself (a shadow ray per observed point and "
                        "direction cell, cast once and cached): off, auto (on where a probe finds the mesh blocking a "
                        "meaningful share of the light; a convex mesh casts nothing) or on. Default: auto with "
                        "per-pixel integrals (a path tracer's or a camera's light), off with the split sum (pbrfit's "
                        "own split-sum renders cast no shadows of the environment); report.json's \"occlusion\" says "
                        "which and its time")
    p.add_argument("--bounce", choices=BOUNCE_MODES,
                   help="with occlusion and per-pixel integrals, whether a blocked direction brings the light the "
                        "capture shows on the surface it hits (light reflected between surfaces, as in a photograph or "
                        "a path tracer's render) or none (a render of direct light only). Default auto: fit both ways "
                        "at pixel centres, keep the one of lower residual; report.json's \"occlusion\" says which")
    p.add_argument("--pixel-samples", metavar="{auto,N}",
                   help=f"shade N x N samples per pixel (N from 1 to {MAX_PIXEL_SAMPLES}) and fit their mean: the pixel "
                        "footprint of an antialiased or supersampled capture (1: pixel centres; cost grows as N^2). Default auto: for "
                        "sRGB or tone-mapped images, fit both 2 x 2 samples and centres and keep the better match; for "
                        "linear HDR ones, pixel centres, and both (with 3 x 3 samples) only where their residuals "
                        "show a box filter's blur")
    p.add_argument("--no-search", action="store_true",
                   help="skip the per-texel re-search of metallic and roughness midway through the solve")
    p.add_argument("--no-repair", action="store_true",
                   help="skip the repair after the solve (by default well-seen texels whose pixels fit worse than "
                        "the noise explains, then those out of line with their neighbours, are started again from "
                        "their nearest well-fitted neighbour, re-searched and re-solved with their neighbours, each "
                        "cluster kept where its pixels fit better and the loss falls; report.json's repair says what "
                        "each pass did)")
    p.add_argument("--unconstrained-sigma", type=float, default=None, metavar="S",
                   help="hold at 0.5 (the middle of its range) the roughness of each texel whose standard error "
                        "exceeds S, and re-fit its base colour: where no highlight reaches a texel the images "
                        "do not constrain its roughness, and a fitted value is the noise's (default 0.1; inf: hold "
                        "none; report.json's unconstrained says how many were held)")
    p.add_argument("--uncertainty-radius", type=int, default=None, metavar="R",
                   help="uncertainty.exr: each texel's standard error with the (2R+1) x (2R+1) texels around it "
                        "free as well (0, 1 or 2; default 1; 0: its own block of the normal matrix, the neighbours "
                        "held, about 10-15%% too small on the peer scene; 2: within 0.1%% of the whole matrix's on a "
                        "small map, about 4 times the cost; see docs/error-bars.md)")
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
                        f"released before the end (default {default_continuation()}; 'none' turns it off)")
    add_model_argument(p)
    p.add_argument("--devices", default="auto", metavar="N|auto",
                   help="split the pixels over this many JAX devices (default auto: every local device of an "
                        "accelerator, one CPU device)")
    p.add_argument("--cache", help="G-buffer and per-pixel IBL cache folder (default $PBRFIT_CACHE, else $XDG_CACHE_HOME/pbrfit, else ~/.cache/pbrfit)")
    p.add_argument("--no-cache", action="store_true", help="do not read or write the cache")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary line; warnings and errors still print")
    p.add_argument("--resume", action="store_true",
                   help="go on from the checkpoint an interrupted fit to the same --out left beside it "
                        "(OUT.pbrfit-checkpoint, kept every few seconds of solving, removed once the output is "
                        "written): the same maps as a fit never interrupted; none there: start afresh; one of "
                        "another capture or other options is refused (report.json's resumed says where it went on)")


def default_continuation() -> str:
    """``--continuation``'s default, the weights `pbrfit.fitting.defaults.CONTINUATION` as given."""
    return ",".join(str(w) for w in CONTINUATION)
