"""Fitting: recover glTF base colour, metallic and roughness maps from a capture.

`fit(capture, ...)` ray-casts the views once (`pbrfit.observations`), then minimises the squared
difference between the images and the renders of the maps, in the images' own space, with the
solver chosen by ``solver=``:

- ``"structured"`` (default): projected Levenberg-Marquardt on the exact image-space objective
  with per-pixel forward-mode Jacobians, block-sparse normal equations and block-Jacobi CG
  (`pbrfit.solvers`), started by a per-texel grid search, then a continuation (the first steps
  under a smoothness prior of falling weight, released before the end), midway re-searching each
  texel's metallic and roughness with its neighbours fixed (`pbrfit.initialisation`); optionally
  coarse to fine (a uniform material first, then maps of growing resolution).
  `experiments/solvers.md` has the numbers that chose it.
- ``"lm"``, ``"gn"``, ``"dogleg"``, ``"bfgs"``, ``"lbfgs"``, ``"ncg"``, ``"adam"``: optimistix
  solvers on the same objective (`pbrfit.optx_solvers`), run through the same schedule.

After the structured solve, a repair (``repair=True``) starts texels whose pixels fit worse than
the noise explains, then texels out of line with their neighbours, again from their neighbours
(`pbrfit.repair`), and the uniform check
(``uniform_check=True``) makes metallic, then roughness, one common value where Akaike's
criterion finds no support for a map in the images (`pbrfit.selection`).

A pixel's footprint: a display-referred capture (sRGB, tone mapped) is fitted both at pixel
centres and with 2 × 2 samples per pixel, and the fit whose images match better is kept
(``pixel_samples="auto"``, `footprint_choice`); linear images are fitted at pixel centres.

The images' noise: plain least squares by default (``noise_level="uniform"``); with
``noise_level="estimated"`` a second fit weighs each residual by the inverse of the noise
level the first fit's residuals show at its value (`pbrfit.noise`): for shot noise, or noise
proportional to the signal.

Pixels can be split over several devices (``devices=``, `pbrfit.sharding`). The result carries
the maps, per-texel standard errors (`pbrfit.uncertainty`), per-texel coverage, the fitted
renders of every view and a report.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import importlib
import inspect
import itertools
import math
import os
import sys
import time
import types
from pathlib import Path
from typing import Callable, Mapping, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .errors import CaptureError
from .initialisation import coordinate_search, grid_initialise, parity_classes
from .material import Material
from .model import Model
from .observations import (MAX_PIXEL_SAMPLES, Observations, TexelLayout, coverage_counts, neighbour_pairs,
                           observations_from_capture, texel_layout, uniform_layout)
from .noise import NOISE_LEVELS, estimate_noise_level
from .optx_solvers import OPTX_SOLVERS, make_solver, optx_solve
from .pixel_ibl import PixelIBLSettings, pixel_ibl
from .repair import (OUTLIER_EVIDENCE, OUTLIER_SPREAD, REPAIR_PASSES, REPAIR_PROGRESS, REPAIR_ROUNDS,
                     REPAIR_STEPS, fill_from_nearest, identifiable_texels, improved_clusters, misfit_texels, outlier_texels,
                     repair_region, texel_misfit, well_seen_texels)
from .parameters import CHANNELS, FIT_GROUPS, NORMAL_CHANNELS, channel_mask, lower, normal_from_slopes, prior, upper
from .sharding import pixel_mesh, shard_problem
from .selection import (NEWTON_STEPS, SELECTABLE, WALD_MARGIN, aic_statistic, newton_value, prefers_uniform,
                        profile_hessian, texel_precisions, uniform_direction, wald_statistic, weighted_value)
from .solvers import (CG_RTOL, LOSSES, Problem, linearize, neighbour_blocks, normal_blocks, objective,
                      pixel_residuals, structured_lm)
from .textures import resample_map, sample_bilinear
from .transfer import to_device
from .uncertainty import (MAX_UNCERTAINTY_RADIUS, WINDOW_RADIUS, residual_variance, window_radii,
                          window_standard_errors)

__all__ = ["fit", "fit_observations", "FitResult", "default_resolution", "map_rmse", "model_for_capture",
           "SOLVERS", "DEFAULT_SOLVER", "IBL_MODES", "CONTINUATION", "SETTLE_STEPS", "RELEASED_STEPS", "continuation_scale", "schedule",
           "footprint_choice", "footprint_energies", "AUTO_PIXEL_SAMPLES", "AUTO_MAX_PIXELS", "PROBE_STEPS",
           "uniform_channels"]

#: The per-texel blocks of JᵀJ, one jitted function for the repair, the uniform check, the
#: preconditioner's scale and the uncertainty (one compile per problem shape).
_normal_blocks = jax.jit(normal_blocks)
#: The blocks between neighbouring texels, for the uncertainty's windows (one compile per map size).
_neighbour_blocks = jax.jit(neighbour_blocks, static_argnums=2)

DEFAULT_SOLVER = "structured"
#: What `fit` may integrate a capture's environment light with (``ibl=``); the first is the default.
IBL_MODES = ("split_sum", "per_pixel")
SOLVERS = (DEFAULT_SOLVER,) + OPTX_SOLVERS
#: Default step limits: per coarse level, and for the final level.
COARSE_STEPS = 20
MAX_STEPS = 40
#: With ``search=True`` the final level runs this many steps, then `coordinate_search`
#: (`SEARCH_ROUNDS` sweeps of the four parity classes), then the rest of its steps
#: (experiments/solvers.md).
SEARCH_AFTER = 15
SEARCH_ROUNDS = 1
#: Continuation (graduated smoothing; A. Blake & A. Zisserman, "Visual Reconstruction", MIT
#: Press 1987, ch. 7): the final level's first `SEARCH_AFTER` steps are split evenly over these
#: weights of a smoothness prior; after the search, `SETTLE_STEPS` more run under the last
#: weight (the search moves texels few pixels see into minima of those few pixels), and the
#: steps after them run on the objective as asked (no prior unless ``smooth`` is set). The prior
#: pulls texels that few pixels pin down, and patches that the grid start put in a wrong
#: roughness basin, towards their neighbours' basin; released, each texel settles in the minimum
#: of its own data there. Weights are relative to the data's mean curvature per texel at the
#: start (`continuation_scale`), so they do not depend on the images' brightness (exactly so for
#: linear images).
#: `experiments/solvers.md` has the numbers that chose them. The structured solver only (the
#: optimistix ones would compile once per phase), and only where at least `RELEASED_STEPS` steps
#: are left without the prior: with fewer (``max_steps`` under 25) there is no continuation, and
#: with fewer after the settling steps (under 30) no settling.
CONTINUATION = (0.0035, 0.00035)
SETTLE_STEPS = 5
RELEASED_STEPS = 10
#: Samples per pixel side that ``pixel_samples="auto"`` tries on display-referred images
#: (`footprint_choice`): 2 × 2 is exact for 2 × 2 supersampled renders and close to finer box
#: averages (experiments/solvers.md, "Pixel footprints").
AUTO_PIXEL_SAMPLES = 2
#: ... and only on captures of at most this many pixels (all frames together; 16 views of 350²):
#: the samples take four times the rows, so about four times the memory and three times the time
#: of pixel centres; beyond it a fit asks for them with ``pixel_samples=2``.
AUTO_MAX_PIXELS = 2_000_000
#: The automatic footprint's early stop: after the centres' last steps, the samples' first
#: `PROBE_STEPS` (the settling ones) run, and where their data term is not yet below the
#: centres' final one the centres are kept without the rest (structured solver; the model the
#: images need gets there at once, experiments/solvers.md).
PROBE_STEPS = SETTLE_STEPS
#: Default scale of the robust losses, in image units (a few times a typical noise level).
LOSS_SCALE = 0.05
#: Each coarse-to-fine level is this factor finer than the one before (see experiments/solvers.md).
LEVEL_FACTOR = 4
#: `default_resolution` picks the finest power of two whose texels are at least this many
#: pixels wide in the median view (below one pixel per texel, neighbours become inseparable).
PIXELS_PER_TEXEL = 1.0
#: ... and at which the observed texels get at least this many pixel observations each, over
#: all views (a texel has 5 unknowns; a pixel gives 3 numbers, and metallic and roughness need
#: several directions).
OBSERVATIONS_PER_TEXEL = 8.0
MAX_RESOLUTION = 2048
#: The uniform check (``uniform_check=True``, `pbrfit.selection`): steps of each re-fit of the
#: other channels at a trial common value (on noisy images they stop at this cap, leaving
#: E_uniform a little high, which leans the test towards the map; the re-fits also continue the
#: map fit's own descent, which leans it the other way where that had not converged), and the
#: Newton step on that value, in units of its standard error, below which the value is final (it
#: moves the test statistic by its square).
REFIT_STEPS = 10
NEWTON_TOL = 1.0


@dataclasses.dataclass
class FitResult:
    """What `fit` returns.

    Attributes:
        material: the fitted maps (`pbrfit.material.Material`; 1 × 1 for a uniform fit), with a
            tangent-space normal map when normals are fitted.
        uncertainty: (H, W, K) one-sigma errors (base R, G, B, metallic, roughness, and the
            normal's slopes s_x, s_y when normals are fitted), each texel's with the texels of
            its window free (``uncertainty_radius``); 0 for fixed channels, +inf for texels no
            view sees.
        coverage: (H, W) pixel observations per texel (0 = never seen; such texels keep `PRIOR`).
        report: model, solver, steps (also as "iterations", the capture spec's word), times
            (setup / compile / solve), final loss, per-view PSNR, devices, the levels run and the
            uniform check's tests.
        images: per view, the fitted render in the images' own space (H, W, 3); targets: the
            images; masks: (H, W) bool, the pixels that entered the objective.
    """

    material: Material
    uncertainty: np.ndarray
    coverage: np.ndarray
    report: dict
    images: list
    targets: list
    masks: list


def model_for_capture(capture, fit: Sequence[str] = ("base_color", "metallic", "roughness"), fixed=None) -> Model:
    """The model the images need: split-sum IBL when there is an environment; the metal lobe
    only when metallic is fitted or fixed to something nonzero."""
    from .views import model_for_capture as scene_model

    fixed = fixed or {}
    metal = "metallic" in fit or bool(np.any(np.asarray(fixed.get("metallic", 0.0)) != 0))
    return scene_model(capture, metallic=metal)


def _ibl_for_capture(capture, model: Model):
    if model.ibl is None and not model.multiscatter:
        return None
    from .views import capture_ibl

    return capture_ibl(capture, model=model)


def _median_footprint(obs: Observations) -> float:
    """Median side (in uv units) of one pixel's footprint on the texture, over all views."""
    uv = np.asarray(obs.pixel_rows(obs.uv))  # one sample per pixel: the pixel grid's spacing
    vidx = np.asarray(obs.pixel_rows(obs.view_index))
    pix = np.asarray(obs.pixel_rows(obs.pixel))
    sides = []
    for view, (h, w) in enumerate(obs.shapes):
        sel = vidx == view
        img = np.full((h * w, 2), np.nan)
        img[pix[sel]] = uv[sel]
        img = img.reshape(h, w, 2)
        du = img[:-1, 1:] - img[:-1, :-1]
        dv = img[1:, :-1] - img[:-1, :-1]
        area = np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
        sides.append(np.sqrt(area[np.isfinite(area)]))
    sides = np.concatenate(sides) if sides else np.zeros(0)
    sides = sides[sides < 0.25]  # seams of the uv layout are not footprints
    return float(np.median(sides)) if sides.size else 1.0


def default_resolution(capture_or_obs) -> int:
    """The finest power-of-two map size whose texels are at least `PIXELS_PER_TEXEL` pixels
    wide, judged by the median pixel footprint in uv over all views, and whose observed texels
    get at least `OBSERVATIONS_PER_TEXEL` pixels each on average (more views allow finer maps).
    The map has no more texels than the views have pixels: views of a small part of the texture
    (close-ups, a narrow field of view) would otherwise ask for a fine map the solve pays for
    whole, almost all of it unseen (pass ``resolution`` for that)."""
    obs = capture_or_obs if isinstance(capture_or_obs, Observations) else observations_from_capture(capture_or_obs)
    side = _median_footprint(obs) * PIXELS_PER_TEXEL
    n = 2 ** int(math.floor(math.log2(max(1.0 / max(side, 1e-9), 1.0))))
    most = 2 ** int(math.floor(math.log2(max(math.sqrt(obs.num_pixels), 1.0))))
    n = int(min(max(n, 1), MAX_RESOLUTION, most))
    while n > 1:
        seen = int(np.sum(coverage_counts(texel_layout(obs, (n, n))) > 0))
        if obs.num_pixels >= OBSERVATIONS_PER_TEXEL * seen:
            break
        n //= 2
    return n


def schedule(resolution: tuple[int, int], factor: int = LEVEL_FACTOR) -> list[tuple[int, int]]:
    """Coarse-to-fine levels: a uniform material (1, 1), then sizes growing by `factor` up to
    `resolution` (each level divides the final size exactly)."""
    h, w = resolution
    levels = [(h, w)]
    while levels[-1][0] % factor == 0 and levels[-1][1] % factor == 0 and min(levels[-1]) // factor >= 4:
        levels.append((levels[-1][0] // factor, levels[-1][1] // factor))
    levels.append((1, 1))
    return list(dict.fromkeys(reversed(levels)))


def _fixed_values(fixed: Mapping, shape: tuple[int, int], k: int = 5) -> np.ndarray:
    """(H, W, k) values of the channels held fixed (`prior` where nothing is given)."""
    out = np.broadcast_to(prior(k), shape + (k,)).copy()
    for name, value in (fixed or {}).items():
        if name not in FIT_GROUPS:
            raise ValueError(f"unknown fixed map {name!r}; expected some of {', '.join(FIT_GROUPS)}")
        chans = list(FIT_GROUPS[name])
        if max(chans) >= k:
            raise ValueError(f"a fixed {name!r} map is not supported: fit it or leave it out")
        v = np.asarray(value, np.float32)
        if v.ndim == 3:
            v = resample_map(v, shape)
        out[..., chans] = np.broadcast_to(v.reshape(v.shape[:-1] + (-1,)) if v.ndim == 3 else v, shape + (len(chans),))
    return out


def uniform_channels(report: dict) -> list[str]:
    """Names of the channels a fit's uniform check made one common value (its report's
    "uniform_check" entries with ``uniform``)."""
    return [name for name, c in report.get("uniform_check", {}).items() if isinstance(c, dict) and c.get("uniform")]


def held_report(fit: Sequence[str], fixed: Optional[Mapping]) -> dict:
    """What each material map not fitted was held at, for the report: ``{"source": "value",
    "value": v}`` (a number, or R, G, B), ``{"source": "map", "shape": [H, W], "mean": m}`` or,
    for a map neither fitted nor given, ``{"source": "prior", "value": v}`` (`PRIOR`)."""
    out = {}
    for name in ("base_color", "metallic", "roughness"):
        if name in fit:
            continue
        chans = list(FIT_GROUPS[name])
        value = None if fixed is None else fixed.get(name)
        if value is None:
            v = [float(c) for c in prior(5)[chans]]
            out[name] = dict(source="prior", value=v if len(v) > 1 else v[0])
        elif np.ndim(value) == 3:
            a = np.asarray(value, np.float64)
            mean = [float(c) for c in a.reshape(-1, a.shape[-1]).mean(0)]
            out[name] = dict(source="map", shape=list(a.shape[:2]), mean=mean if len(mean) > 1 else mean[0])
        else:
            v = [float(c) for c in np.ravel(value)]
            out[name] = dict(source="value", value=v if len(v) > 1 else v[0])
    return out


def _upsample(x: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    uv = np.stack(np.meshgrid(u, v, indexing="xy"), -1)
    return np.asarray(sample_bilinear(jnp.asarray(x), jnp.asarray(uv), "clamp"))


def _layout(obs: Observations, shape, wrap: str) -> TexelLayout:
    return uniform_layout(obs) if tuple(shape) == (1, 1) else texel_layout(obs, shape, wrap)


#: The material maps a fit can fit or hold (``fit=``, ``fixed=``); "normal" can only be fitted.
MATERIAL_MAPS = ("base_color", "metallic", "roughness")
#: The largest finite float32, the solve's precision: the bound of every real-valued option.
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: The largest map side an explicit ``resolution`` takes (the default stops at `MAX_RESOLUTION`).
MAX_MAP_SIDE = 8192
#: The most solver steps ``max_steps`` (and ``coarse_steps``) takes: far beyond any use, and within
#: the int32 step counters of the jitted loops.
MAX_SOLVER_STEPS = 1_000_000


@dataclasses.dataclass(frozen=True)
class OptionNames:
    """How `fit_arguments` and `check_options` name what they refuse: by the Python keyword
    (default: ``smooth``, ``solver='lm'``, ``fixed``) or, with ``flags``, by the command line's
    flag (``--smooth``, ``--solver lm``); ``held_by`` then gives the flag that holds each map
    (``--roughness`` or ``--roughness-from``)."""

    flags: bool = False
    held_by: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def option(self, name: str) -> str:
        return "--" + name.replace("_", "-") if self.flags else name

    def setting(self, name: str, value) -> str:
        return f"{self.option(name)} {value}" if self.flags else f"{name}={value!r}"

    def holder(self, name: str) -> str:
        """Who holds map ``name``: its flag, or the ``fixed`` argument."""
        return self.held_by.get(name, self.option(name)) if self.flags else "fixed"

    def held_value(self, name: str) -> str:
        return self.holder(name) if self.flags else f"fixed[{name!r}]"


def fit_arguments(fit=None, fixed: Optional[Mapping] = None,
                  names: OptionNames = OptionNames()) -> tuple[tuple[str, ...], dict]:
    """The maps a fit frees and the values it holds, checked (`ValueError` otherwise, worded
    with ``names``).

    ``fit``: names from `FIT_GROUPS` (a sequence, or one string of comma-separated names); None
    (default): every map of `MATERIAL_MAPS` that ``fixed`` does not hold. ``fixed``: {map: value}
    for maps of `MATERIAL_MAPS`, finite and in [0, 1]: base colour as one grey value, R, G, B or an
    (H, W, 3) map; metallic and roughness as one value or an (H, W) or (H, W, 1) map (any size:
    resampled to the fit's by `pbrfit.textures.resample_map`). A map may not be both fitted and
    held, and something must be fitted.
    Returns (fit, fixed) with the held values as float32 arrays of shape (), (3,), (H, W, C)."""
    held = {}
    for name, value in dict(fixed or {}).items():
        if name not in MATERIAL_MAPS:
            raise ValueError(f"fixed: unknown map {name!r}; expected some of {', '.join(MATERIAL_MAPS)}"
                             + (" (a normal map can only be fitted)" if name == "normal" else ""))
        label = names.held_value(name)
        try:
            v = np.asarray(value)
            if v.dtype.kind not in "biuf":
                raise TypeError
            v = v.astype(np.float32)
        except (TypeError, ValueError):
            raise ValueError(f"{label}: expected numbers, got {value!r}") from None
        channels = len(FIT_GROUPS[name])
        if name != "base_color" and v.ndim == 2:
            v = v[..., None]
        ok = v.ndim == 0 or (v.ndim == 1 and v.shape[0] in (1, channels)) or (
            v.ndim == 3 and v.shape[-1] == channels and min(v.shape[:2]) >= 1)
        if not ok:
            want = "a value, R, G, B or an (H, W, 3) map" if channels == 3 else "a value or an (H, W) map"
            raise ValueError(f"{label}: expected {want}, got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{label}: holds NaN or inf")
        if np.any(v < 0.0) or np.any(v > 1.0):
            found = f"got {v.item():g}" if v.size == 1 else f"found {v.min():g} to {v.max():g}"
            raise ValueError(f"{label}: expected values in [0, 1], {found}")
        held[name] = v.reshape(-1)[0] if v.ndim == 1 and v.shape[0] == 1 else v
    option = names.option("fit")
    if fit is None:
        fit = tuple(name for name in MATERIAL_MAPS if name not in held)
    else:
        listed = fit.split(",") if isinstance(fit, str) else list(fit)
        fit = tuple(str(name).strip() for name in listed if str(name).strip())
        for name in fit:
            if name not in FIT_GROUPS:
                raise ValueError(f"{option}: unknown map {name!r}; expected some of {', '.join(FIT_GROUPS)}")
            if fit.count(name) > 1:
                raise ValueError(f"{option}: lists {name} twice")
            if name in held:
                raise ValueError(f"{option}: lists {name}, which {names.holder(name)} holds too; drop one of the two")
    if not fit:
        why = "every map is held fixed" if held and len(held) == len(MATERIAL_MAPS) else "it names no map"
        raise ValueError(f"{option}: nothing to fit ({why})")
    return fit, held


def check_options(*, resolution, maps, solver, max_steps, coarse_steps, rtol, atol, cg_rtol, loss_scale, smooth,
                  coarse_to_fine, continuation, uncertainty_radius, names: OptionNames = OptionNames()) -> None:
    """`ValueError` (worded with ``names``) for option values out of range, or given to a mode
    that does not read them: `fit`, `fit_observations` and the command line refuse alike."""
    say = names.option
    if resolution is not None:
        sides = [resolution] if np.ndim(resolution) == 0 else list(np.ravel(resolution))
        if (np.ndim(resolution) != 0 and len(sides) != 2) or any(
                isinstance(r, (bool, np.bool_)) or not isinstance(r, (int, np.integer)) or not 1 <= r <= MAX_MAP_SIDE
                for r in sides):
            want = "an integer" if names.flags else "an integer N or a pair (H, W) of integers"
            raise ValueError(f"{say('resolution')}: must be {want} from 1 to {MAX_MAP_SIDE}, got {resolution!r}")
    for name, value, least in (("max_steps", max_steps, 1), ("coarse_steps", coarse_steps, 0),
                               ("uncertainty_radius", uncertainty_radius, 0)):
        most = MAX_UNCERTAINTY_RADIUS if name == "uncertainty_radius" else MAX_SOLVER_STEPS
        if value is None and name == "max_steps":  # the solver's own default
            continue
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or not least <= value <= most:
            raise ValueError(f"{say(name)}: must be an integer from {least} to {most}, got {value!r}")
    for name, value in (("rtol", rtol), ("atol", atol), ("smooth", smooth)):
        if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{say(name)}: must be a finite number >= 0, got {value!r}")
        if value > FLOAT32_MAX:  # the solve runs in float32
            raise ValueError(f"{say(name)}: must be at most {FLOAT32_MAX:.3g} (float32), got {value!r}")
    weights = () if continuation is None else np.ravel(np.asarray(continuation, dtype=object))
    if not all(isinstance(w, (int, float, np.number)) and not isinstance(w, (bool, np.bool_)) and math.isfinite(w)
               and 0 <= w <= FLOAT32_MAX for w in weights):
        raise ValueError(f"{say('continuation')}: expected weights >= 0 within float32, got {continuation!r}")
    if not (isinstance(loss_scale, (int, float, np.number)) and math.isfinite(loss_scale) and loss_scale > 0):
        raise ValueError(f"{say('loss_scale')}: must be a finite number > 0, got {loss_scale!r}")
    if not (isinstance(cg_rtol, (int, float, np.number)) and 0.0 < cg_rtol < 1.0):
        raise ValueError(f"{say('cg_rtol')}: must be a number in (0, 1), got {cg_rtol!r}")
    given_continuation = continuation is not None and len(np.ravel(continuation)) > 0 \
        and tuple(np.ravel(continuation)) != CONTINUATION
    if solver != DEFAULT_SOLVER:  # options only the structured solver reads
        for name, given in (("cg_rtol", cg_rtol != CG_RTOL), ("continuation", given_continuation)):
            if given:
                raise ValueError(f"{say(name)}: only the {DEFAULT_SOLVER} solver uses it, "
                                 f"not {names.setting('solver', solver)}")
    if maps == "none":  # one texel: no map size, no neighbours, no levels
        for name, given in (("resolution", resolution is not None), ("smooth", smooth > 0),
                            ("continuation", given_continuation), ("coarse_to_fine", coarse_to_fine)):
            if given:
                raise ValueError(f"{say(name)}: {names.setting('maps', 'none')} fits one uniform material (1 x 1 maps)")


def _check_normals(model: Model, fit: Sequence[str]) -> None:
    if model.ibl == "per_pixel" and "normal" in fit:
        raise ValueError("fitting normals needs ibl='split_sum': per-pixel IBL integrals hold each pixel's normal fixed")


def fit_observations(
    obs: Observations,
    *,
    model: Model = Model(),
    ibl=None,
    resolution=None,
    fit: Optional[Sequence[str]] = None,
    fixed: Optional[Mapping] = None,
    maps: str = "texture",
    solver: str = DEFAULT_SOLVER,
    max_steps: Optional[int] = None,
    coarse_steps: int = COARSE_STEPS,
    rtol: float = 1e-6,
    atol: float = 1e-5,
    cg_rtol: float = CG_RTOL,
    loss: str = "l2",
    loss_scale: float = LOSS_SCALE,
    smooth: float = 0.0,
    coarse_to_fine: bool = False,
    init: str = "grid",
    search: bool = True,
    continuation: Optional[Sequence[float]] = CONTINUATION,
    devices=None,
    level_factor: int = LEVEL_FACTOR,
    wrap: str = "repeat",
    progress: Optional[Callable] = None,
    setup_time: float = 0.0,
    centres: Optional[Observations] = None,
    centre_ibl=None,
    select_footprint: bool = False,
    background_compile: bool = True,
    uniform_check: bool = True,
    repair: bool = True,
    uncertainty_radius: int = WINDOW_RADIUS,
    noise_level: str = "uniform",
) -> FitResult:
    """Fit maps to prepared `Observations` (see `fit` for the arguments).

    The light is the caller's to describe: ``model`` and ``ibl`` must be those of the capture
    the observations come from (`fit` derives them: `model_for_capture`, and
    `pbrfit.views.capture_ibl` or `pbrfit.pixel_ibl.pixel_ibl`). The defaults, ``Model()`` and no
    tables, shade with the observations' punctual lights alone, so a capture lit by an
    environment is fitted as if that light were absent.

    With several samples per pixel in `obs`, `centres` (optional) holds the same capture's
    observations at pixel centres (and `centre_ibl` their IBL, when it is per pixel): the grid
    start, the continuation's first steps and the coordinate search then run on them, at a
    quarter of the cost or less, and only the settling and released steps on `obs`. With
    ``select_footprint`` as well, those last steps run on both, from the same point (centres
    first), and the fit whose data term is lower over the pixels both use is kept
    (`footprint_energies`; both have the same parameters, so that is the likelier model of the
    pixels' footprint). With the structured solver the samples stop after their first
    `PROBE_STEPS` when these do not yet fit better than the centres' whole finish. The report's
    "footprint" entry gives both energies, the steps and the choice."""
    _check_names(noise_level=noise_level, loss=loss, init=init, wrap=wrap)
    _check_kinds(**{name: value for name, value in locals().items() if name in _KIND_DEFAULTS})
    fit, fixed = fit_arguments(fit, fixed)
    _check_model(model, fit)
    check_options(resolution=resolution, maps=maps, solver=solver, max_steps=max_steps, coarse_steps=coarse_steps,
                  rtol=rtol, atol=atol, cg_rtol=cg_rtol, loss_scale=loss_scale, smooth=smooth,
                  coarse_to_fine=coarse_to_fine, continuation=continuation, uncertainty_radius=uncertainty_radius)
    kwargs = {name: value for name, value in locals().items() if name not in ("obs", "noise_level")}  # the arguments
    if noise_level == "uniform":
        result, _ = _fit_pass(obs, **kwargs)
        result.report["noise_level"] = dict(mode="uniform")
    else:
        result = _fit_weighted(obs, kwargs)
    result.report["iterations"] = result.report["steps"]  # the capture spec's word for them
    return result


def _check_kinds(*, progress, level_factor, devices, **switches) -> None:
    """`ValueError` for arguments of the wrong kind, before any work: a switch that is not a
    bool (``search="no"`` read as true), a ``progress`` that cannot be called (it failed inside
    the compiled solve), a ``level_factor`` below 2, ``devices`` that are not JAX devices."""
    for name, value in switches.items():
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name}: expected True or False, got {value!r}")
    if progress is not None and not callable(progress):
        raise ValueError(f"progress: expected a function of one dict, or None, got {progress!r}")
    if isinstance(level_factor, (bool, np.bool_)) or not isinstance(level_factor, (int, np.integer)) \
            or level_factor < 2:
        raise ValueError(f"level_factor: expected an integer >= 2, got {level_factor!r}")
    if devices is not None:
        try:
            listed = [devices] if isinstance(devices, (str, bytes, jax.Device)) else list(devices)
        except TypeError:
            listed = [devices]
        if isinstance(devices, (str, bytes, jax.Device)) or not listed \
                or not all(isinstance(d, jax.Device) for d in listed):
            raise ValueError(f"devices: expected a sequence of JAX devices (jax.devices()), got {devices!r}")


def _check_names(*, noise_level, loss, init, wrap, pixel_samples="auto") -> None:
    """`ValueError` for a named choice out of its list (`fit_observations`; `pbrfit.fit` before
    it reads the capture and casts its rays, with ``pixel_samples`` too)."""
    from .observations import MAX_PIXEL_SAMPLES
    from .textures import WRAPS

    for name, value, choices in (("noise_level", noise_level, NOISE_LEVELS), ("loss", loss, LOSSES),
                                 ("init", init, ("grid", "prior")), ("wrap", wrap, WRAPS)):
        if not isinstance(value, str) or value not in choices:
            raise ValueError(f"{name} must be one of {', '.join(choices)}, got {value!r}")
    whole = isinstance(pixel_samples, (int, np.integer)) and not isinstance(pixel_samples, (bool, np.bool_))
    if pixel_samples != "auto" and not (whole and 1 <= pixel_samples <= MAX_PIXEL_SAMPLES):
        raise ValueError(f"pixel_samples must be 'auto' or an integer from 1 to {MAX_PIXEL_SAMPLES}, "
                         f"got {pixel_samples!r}")


def _check_model(model, fit: Sequence[str]) -> None:
    """`ValueError` for a ``model`` that is not a `Model`, or that has no metal lobe while
    metallic is fitted."""
    if not isinstance(model, Model):
        raise ValueError(f"model: expected a pbrfit.Model, got {model!r}")
    if "metallic" in fit and not model.metallic:
        raise ValueError("fit: metallic is fitted, and the model has no metal lobe (Model(metallic=False)): "
                         "the images could not say anything about it")


#: `fit_observations`'s defaults of the options `check_options` checks.
_OPTION_DEFAULTS = {name: param.default for name, param in inspect.signature(fit_observations).parameters.items()
                    if name in inspect.signature(check_options).parameters}
#: ... and of those `_check_kinds` checks.
_KIND_DEFAULTS = {name: inspect.signature(fit_observations).parameters[name].default
                  for name in ("coarse_to_fine", "search", "select_footprint", "background_compile", "uniform_check",
                               "repair", "progress", "level_factor", "devices")}


def _fit_weighted(obs: Observations, kwargs: dict) -> FitResult:
    """``noise_level="estimated"`` (`pbrfit.noise`): a plain fit, the noise level function of its
    residuals, and a second fit from the first's maps with each residual weighted by
    σ_ref / σ(v̂) at the first fit's value v̂. The second fit runs the final level on the pixel
    footprint the first chose, with the uniform check (whose outcome the weights may change)
    but without the continuation, the coordinate search, the repair or steps on pixel centres:
    it starts in the basins the first fit found (on the flash scene with relative noise,
    running the search and repair again took the estimated fit to 155 s against 98 s, the maps
    the same to within 0.001). Executables compiled for the first fit serve the second. The
    report is the second fit's, with both fits' steps and times, the first fit's "repair" entry,
    and a "noise_level" entry: the level function and the first fit's steps, loss, residual σ,
    levels and continuation."""
    t_start = time.perf_counter()
    shared = {}
    first, x = _fit_pass(obs, shared=shared, **kwargs)
    footprint = first.report.get("footprint")
    centres = kwargs["centres"]
    kept = centres if (obs.samples > 1 and footprint is not None and footprint.get("selected") == 1) else obs
    values = _fitted_values(first, kept)
    target = np.asarray(kept.pixel_rows(kept.target))
    n_res = values.size
    uniform = len(uniform_channels(first.report))
    n_par = (len(first.report["fitted"]) - uniform) * first.report["observed_texels"] + uniform  # as `_finish` counts
    level = estimate_noise_level(values, values - target, dof_scale=n_res / max(n_res - n_par, 1))
    weights = np.repeat(level.weights(values), kept.samples, axis=0)
    weighted = dataclasses.replace(kept, residual_weight=to_device(weights, np.float32))
    shared["where"].clear()
    shared["where"]["weighted"] = True  # every step from here on reports it
    second_kwargs = dict(kwargs, centres=None, centre_ibl=None, select_footprint=False, start=x,
                         coarse_to_fine=False, continuation=None, search=False, repair=False, setup_time=0.0)
    if kept is centres and kwargs["model"].ibl == "per_pixel":  # the centres' own integrals
        second_kwargs["ibl"] = kwargs["centre_ibl"]
    second, _ = _fit_pass(weighted, shared=shared, **second_kwargs)
    report = second.report
    report["times"] = dict(report["times"], setup=float(kwargs["setup_time"]),
                           post=first.report["times"].get("post", 0.0) + report["times"].get("post", 0.0))
    report["wall_time"] = float(kwargs["setup_time"] + time.perf_counter() - t_start)
    report["steps"] += first.report["steps"]
    if footprint is not None:
        report["footprint"] = footprint
    if "repair" in first.report:
        report["repair"] = first.report["repair"]
    report["noise_level"] = dict(mode="estimated", **level.describe(), first_fit=dict(
        steps=first.report["steps"], final_loss=first.report["final_loss"],
        residual_sigma=first.report["residual_sigma"], psnr=first.report["psnr"], levels=first.report["levels"],
        continuation=first.report["continuation"]))
    return second


def _fitted_values(result: FitResult, obs: Observations) -> np.ndarray:
    """(P, 3) the fitted render's value at each pixel of `obs` (its first sample row's view and
    pixel; `obs` is the footprint the fit kept, every pixel of which it rendered)."""
    vidx = np.asarray(obs.pixel_rows(obs.view_index))
    pix = np.asarray(obs.pixel_rows(obs.pixel))
    values = np.zeros((obs.num_pixels, 3), np.float32)
    for view in range(len(result.images)):
        sel = vidx == view
        values[sel] = result.images[view].reshape(-1, 3)[pix[sel]]
    return values


def _fit_pass(obs: Observations, *, model, ibl, resolution, fit, fixed, maps, solver, max_steps, coarse_steps, rtol,
              atol, cg_rtol, loss, loss_scale, smooth, coarse_to_fine, init, search, continuation, devices,
              level_factor, wrap, progress, setup_time, centres, centre_ibl, select_footprint, background_compile,
              uniform_check, repair, uncertainty_radius, start=None, shared=None) -> tuple[FitResult, np.ndarray]:
    """One fit (`fit_observations`): the result and the final (T, K) texel values. ``start``:
    (T, K) values to start from at the final level (no grid start, no coarser levels);
    ``shared``: a dict that keeps the solver runner, its compiler (whose clock collects every
    pass's times) and the progress callback's ``where`` from one pass to the next (empty: this
    pass makes them)."""
    t_start = time.perf_counter()
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; expected one of {', '.join(SOLVERS)}")
    if maps not in ("texture", "none"):
        raise ValueError(f"maps must be 'texture' or 'none', got {maps!r}")
    _check_normals(model, fit)
    fixed = dict(fixed or {})
    # what the caller held (before the model's own: a model without the metal lobe holds metallic 0)
    held = held_report([f for f in fit if model.metallic or f != "metallic"], fixed)
    channels = channel_mask(fit)
    k = len(channels)
    if not model.metallic:
        channels[3] = 0.0
        fixed.setdefault("metallic", 0.0)
    if maps == "none":
        final = (1, 1)
    else:
        res = default_resolution(obs) if resolution is None else resolution
        final = (int(res), int(res)) if np.isscalar(res) else tuple(int(r) for r in res)
    levels = schedule(final, level_factor) if coarse_to_fine and start is None else [final]
    t_final = final[0] * final[1]
    max_steps = MAX_STEPS if max_steps is None else int(max_steps)
    pairs_final = neighbour_pairs(final)
    e_final = pairs_final.shape[0]

    if select_footprint and (centres is None or obs.samples == 1):
        raise ValueError("select_footprint needs observations with several samples per pixel and their centres")
    if centres is not None and obs.samples > 1 and model.ibl == "per_pixel" and centre_ibl is None:
        raise ValueError("centres with a per-pixel IBL model need centre_ibl: the centres' own integrals")
    mesh = None if devices is None else pixel_mesh(devices)
    continuation = () if continuation is None else tuple(float(w) for w in np.ravel(continuation))  # check_options checked them
    x = None if start is None else np.asarray(start, np.float32).reshape(final + (k,))
    history = []
    annealed = footprint = None
    if shared is None:
        shared = {}
    if "runner" not in shared:
        where = dict(level=0, resolution=levels[0])
        cb = None if progress is None else (
            lambda step, value: progress(dict(where, step=int(step), loss=float(value))))
        compiler = _Compiler(dict(compile=0.0, solve=0.0), background_compile)
        shared.update(where=where, runner=_Runner(solver, rtol, atol, cb, compiler, cg_rtol))
    # (an executable keeps the callback it was compiled with: a later pass reports through the
    # same one, so it tells that callback where it is through the same `where`)
    where, runner = shared["where"], shared["runner"]
    where.update(level=0, resolution=levels[0])
    compiler = runner.compiler
    clock = compiler.clock
    try:
        for level, shape in enumerate(levels):
            where.update(level=level, resolution=tuple(shape))
            layout = _layout(obs, shape, wrap)
            cov = coverage_counts(layout).reshape(-1)
            t = shape[0] * shape[1]
            seen = np.zeros(t_final, bool)
            seen[:t] = cov > 0
            free = (seen[:, None] * channels[None, :]).astype(np.float32)
            fixed_x = np.broadcast_to(prior(k), (t_final, k)).copy()
            fixed_x[:t] = _fixed_values(fixed, shape, k).reshape(t, k)
            x0 = fixed_x.copy()
            if x is not None:
                up = (x if x.shape[:2] == tuple(shape) else _upsample(x, shape)).reshape(t, k)
                x0[:t] = np.where(channels[None, :] > 0, up, x0[:t])
            x0[:t] = np.where(seen[:t, None], x0[:t], fixed_x[:t])
            last = level == len(levels) - 1
            steps = max_steps if last else min(coarse_steps, max_steps)
            head = min(SEARCH_AFTER, steps)
            maps_level = shape != (1, 1)
            searching = last and search and maps_level and np.any(channels[3:] > 0) and head < steps
            annealing = (last and maps_level and solver == DEFAULT_SOLVER and any(w > 0 for w in continuation)
                         and steps - head >= RELEASED_STEPS)
            prior_on = maps_level and (smooth > 0 or annealing)
            pairs, pw = _neighbour_weights(shape, seen, e_final, prior_on)
            problem = Problem(obs, layout.index, layout.weight, to_device(free), to_device(pairs), to_device(pw),
                              to_device(smooth, np.float32), to_device(loss_scale, np.float32), ibl, model, loss)
            if mesh is not None:
                problem = shard_problem(problem, mesh)
            early = problem  # the start, the continuation's steps and the search
            if centres is not None and obs.samples > 1 and (last or (level == 0 and init == "grid" and start is None)):
                lay = _layout(centres, shape, wrap)
                # the texels the centres see are free here (as in a fit of centres alone); texels only
                # samples read keep their start until the samples' steps, and texels only centres read
                # (where some sample misses the mesh) go back to their fixed values for those steps
                centre_seen = np.zeros(t_final, bool)
                centre_seen[:t] = coverage_counts(lay).reshape(-1) > 0
                c_pairs, c_pw = _neighbour_weights(shape, centre_seen, e_final, prior_on)
                centre_free = (centre_seen[:, None] * channels[None, :]).astype(np.float32)
                early = dataclasses.replace(problem, obs=centres, index=lay.index, weight=lay.weight,
                                            free=to_device(centre_free),
                                            pairs=to_device(c_pairs), pair_weight=to_device(c_pw),
                                            ibl=centre_ibl if model.ibl == "per_pixel" else ibl)
                if mesh is not None:
                    early = shard_problem(early, mesh)
            num_free = int(np.sum(free))
            x0 = to_device(x0, np.float32)
            classes = to_device(parity_classes(shape)) if searching else None
            search_key = ("search", shape) + _problem_key(early)
            search_static = (SEARCH_ROUNDS, bool(channels[3] > 0))
            selecting = last and select_footprint
            # compiles this level needs, in the order of their first use, overlap the work before it
            if early is problem or annealing or searching or selecting:  # else only the grid start runs on it
                runner.prefetch(x0, early, num_free)
            if searching:
                compiler.prefetch(search_key, coordinate_search, x0, early, classes, *search_static)
            if early is not problem:
                runner.prefetch(x0, problem, num_free)
            if level == 0 and init == "grid" and start is None:
                x0 = to_device(np.asarray(_timed(compiler, ("grid",) + _problem_key(early), grid_initialise, "init",
                                                 x0, early)), np.float32)
            xs, info = x0, None
            if annealing:
                jac = runner.jacobian(xs, early, num_free)  # timed as compile and solve
                t0 = time.perf_counter()
                scale = continuation_scale(jac, early)
                clock["init"] = clock.get("init", 0.0) + time.perf_counter() - t0
                weights = [w * scale for w in continuation]
                for w, n in zip(weights, (len(a) for a in np.array_split(np.arange(head), len(weights)))):
                    if n > 0:
                        xs, info = _merge(info, runner(to_device(xs, np.float32), with_smooth(early, smooth + w), n,
                                                       num_free))
                annealed = dict(relative=list(continuation), weights=weights, curvature=scale, steps=head,
                                settle_steps=0)
            elif searching:
                xs, info = _merge(info, runner(xs, early, head, num_free))
            done = head if (annealing or searching) else 0
            settle = False
            if searching:
                xn = np.asarray(_timed(compiler, search_key, coordinate_search, "search", to_device(xs, np.float32),
                                       early, classes, *search_static))
                info["search_moved"] = int(np.sum(np.any(xn[:t] != np.asarray(xs)[:t], axis=1)))
                xs = xn
                settle = annealing and weights[-1] > 0 and steps - done - SETTLE_STEPS >= RELEASED_STEPS
                if settle:
                    annealed["settle_steps"] = SETTLE_STEPS

            tail = dict(steps=steps - done, num_free=num_free, settle_weight=smooth + weights[-1] if settle else None)
            if selecting:  # the same steps at pixel centres first, from the same point
                where["footprint"] = 1
                x_c, info_c, lin_c = _finish_level(runner, early, xs, info, **tail)
                r_c = _final_residuals(x_c, early, lin_c)
                where["footprint"] = n_side = _samples_side(obs)
            if early is not problem:
                xs = np.where(seen[:, None], xs, fixed_x)
            probing = selecting and solver == DEFAULT_SOLVER and tail["steps"] > PROBE_STEPS
            stopped = False
            if probing:  # the samples' first steps, then a look at how well they fit already
                xs, info, linearization = _finish_level(runner, problem, xs, info, **dict(tail, steps=PROBE_STEPS))
                stopped = _centres_explain_better(footprint_energies(obs, linearization[0], centres, r_c))
                if not stopped:
                    xs, info, linearization = _finish_level(runner, problem, xs, info, tail["steps"] - PROBE_STEPS,
                                                            num_free)
            else:
                xs, info, linearization = _finish_level(runner, problem, xs, info, **tail)
            if selecting:
                where.pop("footprint")
                e_samples, e_centres, common = footprint_energies(
                    obs, _final_residuals(xs, problem, linearization), centres, r_c)
                footprint = dict(selected=n_side, energies={str(n_side): e_samples, "1": e_centres}, pixels=common,
                                 steps={str(n_side): info["steps"], "1": info_c["steps"]}, stopped_early=stopped)
                if _centres_explain_better((e_samples, e_centres)):
                    footprint["selected"] = 1
                    # texels only samples read are unseen here: their fixed values, as in a fit of centres alone
                    xs, info, linearization = np.where(centre_seen[:, None], x_c, fixed_x), info_c, lin_c
                    obs, problem, seen = centres, early, centre_seen
            history.append(dict(resolution=list(shape), **info))
            x = xs[:t].reshape(shape + (k,))
        repaired = None
        if repair:
            skipped = _repair_skipped(solver, final, channels)
            if skipped is not None:
                repaired = dict(skipped=skipped)
            else:
                xs, linearization, repaired = _repair(runner, compiler, problem, xs, linearization, final, seen,
                                                      channels, num_free, where)
                x = xs[:t_final].reshape(final + (k,))
        checks, uniform = {}, {}
        if uniform_check:
            skipped = _uniform_check_skipped(solver, loss, smooth, final, channels)
            if skipped is not None:
                checks = dict(skipped=skipped)
            else:
                xs, linearization, problem, checks, uniform = _uniform_check(
                    runner, problem, xs, linearization, channels, seen, obs.num_pixels, where)
                x = xs[:t_final].reshape(final + (k,))
    finally:
        compiler.close()

    t_post = time.perf_counter()
    result = _finish(obs, problem, x, final, channels, seen[:t_final], model, solver, history, loss, smooth,
                     dict(setup=setup_time, **clock), t_post, t_start, linearization, wrap, uniform,
                     int(uncertainty_radius))
    if uniform_check:
        for name, c in SELECTABLE:  # the value's σ as uncertainty holds it: the kept fit's residual variance
            if checks.get(name, {}).get("uniform"):
                checks[name]["sigma"] = float(np.asarray(result.uncertainty)[..., c][seen[:t_final].reshape(final)][0])
        result.report["uniform_check"] = checks
        result.report["steps"] += sum(c.get("steps", 0) for c in checks.values() if isinstance(c, dict))
    if repair:
        result.report["repair"] = repaired
        result.report["steps"] += sum(p.get("steps", 0) for p in repaired.get("passes", ()))
    result.report["continuation"] = annealed
    result.report["held"] = held
    if solver == DEFAULT_SOLVER:
        result.report["cg_rtol"] = float(cg_rtol)
    if footprint is not None:
        result.report["footprint"] = footprint
    return result, np.asarray(xs, np.float32)[:t_final]


def _repair_skipped(solver, final, channels) -> Optional[str]:
    """Why the basin repair does not apply to a fit, or None where it does."""
    if tuple(final) == (1, 1):
        return "a uniform material"
    if solver != DEFAULT_SOLVER:
        return f"needs the {DEFAULT_SOLVER} solver"
    if not np.any(np.asarray(channels) > 0):
        return "no channel is fitted"
    return None


def _energy(residuals, x, problem: Problem) -> float:
    """The objective at x from its residuals (the prior's term evaluated where it is on)."""
    if float(problem.smooth) > 0:
        return float(jax.jit(objective)(to_device(x, np.float32), problem))
    return 0.5 * float(np.sum(np.square(np.asarray(residuals, np.float64))))


def _repair(runner, compiler, problem: Problem, xs, linearization, shape, seen, channels, num_free: int,
            where: dict):
    """Texels the solve left in a wrong basin, started again from their neighbours
    (`pbrfit.repair`): (x, linearisation, report). Each pass flags texels, copies into them the
    nearest unflagged one's values, runs the coordinate search and `REPAIR_STEPS` steps over the
    flagged texels and their neighbours (all others held), puts back the clusters whose pixels do
    not fit better (`improved_clusters`), and is kept where the objective then falls. The misfit
    passes flag the well-seen identifiable texels whose pixels fit worse than the noise explains
    (`misfit_texels`) and go on while one lowers the objective by more than `REPAIR_PROGRESS`, up
    to `REPAIR_PASSES`; then one pass flags the identifiable texels out of line with their
    neighbours (`outlier_texels`) and keeps a cluster only where its pixels' Σ ||r||² fell by more
    than (`OUTLIER_EVIDENCE` + `OUTLIER_SPREAD` √(2p)) residual variances, p its free channels.
    Each report entry's "kind" says which."""
    t = shape[0] * shape[1]
    seen_t = np.asarray(seen[:t], bool)
    obs = problem.obs
    scale = float(np.mean(np.square(np.asarray(obs.pixel_rows(obs.target), np.float64))))
    index, weight, free = np.asarray(problem.index), np.asarray(problem.weight), np.asarray(problem.free)
    fitted = np.asarray(channels) > 0
    classes = to_device(parity_classes(shape))
    key = ("repair", tuple(shape)) + _problem_key(problem)
    static = (REPAIR_ROUNDS, bool(channels[3] > 0))
    xs = np.asarray(xs, np.float32)
    energy = _energy(linearization[0], xs, problem)
    passes = []

    def judged():
        """(misfit flags, well-seen identifiable texels, identifiable texels) at the current
        linearisation."""
        r, jac = linearization
        mean, count = texel_misfit(np.asarray(r), index, weight, problem.samples, problem.num_texels)
        blocks = np.asarray(_normal_blocks(jac, problem))[:t]
        identifiable = identifiable_texels(blocks, fitted, seen_t)
        trusted = well_seen_texels(count[:t], seen_t) & identifiable
        return misfit_texels(mean[:t], count[:t], seen_t, scale) & trusted, trusted, identifiable

    def run_pass(kind, flagged, trusted, margin, spread=0.0):
        """One pass over ``flagged``: its report entry appended, and whether it was kept."""
        nonlocal xs, linearization, energy
        entry = dict(kind=kind, flagged=int(np.sum(flagged)))
        passes.append(entry)
        if not np.any(flagged):
            return False
        moving = np.zeros(problem.num_texels, bool)
        moving[:t] = repair_region(flagged, trusted, tuple(shape))
        region = dataclasses.replace(problem, free=jax.device_put(free * moving[:, None], problem.free.sharding))
        y = fill_from_nearest(xs, flagged, trusted, tuple(shape), free)
        where["repair"] = len(passes)
        y = _timed(compiler, key, coordinate_search, "repair", to_device(y, np.float32), region, classes, *static)
        y, info = runner(to_device(y, np.float32), region, REPAIR_STEPS, num_free)
        # residuals and pixel Jacobians do not depend on which texels move: the full problem's
        after = runner.linearization
        better, clusters, improved = improved_clusters(moving, linearization[0], after[0], index, weight,
                                                       problem.samples, margin, spread, np.sum(free > 0, axis=1))
        z = np.asarray(y, np.float32)
        if improved and not np.array_equal(better, moving):
            # the other clusters back where they were, linearised there (step 0, still tagged "repair")
            z = np.where(better[:, None], z, xs)
            runner(to_device(z, np.float32), problem, 0, num_free)
            after = runner.linearization
        where.pop("repair")
        e_after = _energy(after[0], z, problem)
        kept = improved > 0 and e_after < energy
        entry.update(moved=int(np.sum(moving)), clusters=clusters, clusters_kept=improved if kept else 0,
                     texels_kept=int(np.sum(better)) if kept else 0, energy_before=energy, energy_after=e_after,
                     steps=info["steps"], kept=bool(kept))
        if kept:
            xs, linearization, energy = z, after, e_after
        return kept

    misfit, trusted, identifiable = judged()
    for _ in range(REPAIR_PASSES):
        if not np.any(misfit):
            break
        before = energy
        if not run_pass("misfit", misfit, trusted, 0.0):
            break  # nothing moved: the flags below are those at hand
        misfit, trusted, identifiable = judged()
        if before - energy <= REPAIR_PROGRESS * before:
            break
    # the material channels only: a normal map's slopes span a wider range, and bump detail is out
    # of line with its neighbours by nature. Well seen or not: a wrong basin hides in a corner
    # that few pixels read as well.
    material = fitted & (np.arange(fitted.size) < len(CHANNELS))
    sigma2 = residual_variance(energy, 3 * obs.num_pixels, num_free)
    run_pass("outliers", outlier_texels(xs[:t], material, identifiable, tuple(shape)), identifiable,
             OUTLIER_EVIDENCE * sigma2, OUTLIER_SPREAD * sigma2)
    return xs, linearization, dict(passes=passes)


def _uniform_check_skipped(solver, loss, smooth, final, channels) -> Optional[str]:
    """Why the uniform check does not apply to a fit, or None where it does."""
    if tuple(final) == (1, 1):
        return "a uniform material"
    if solver != DEFAULT_SOLVER:
        return f"needs the {DEFAULT_SOLVER} solver"
    if loss != "l2":
        return f"needs the l2 loss (the test reads the data term as a Gaussian likelihood), not {loss}"
    if smooth > 0:
        return "the smoothness prior already ties the texels together"
    if not any(channels[c] > 0 for _, c in SELECTABLE):
        return "neither metallic nor roughness is fitted"
    return None


def _uniform_check(runner, problem: Problem, xs, linearization, channels, seen, num_pixels: int, where: dict):
    """Metallic, then roughness, as one common value where Akaike's criterion prefers it to a map
    (`pbrfit.selection`): (x, linearisation, problem, report, uniform) of the model kept, with
    ``uniform`` {channel: value} of the channels made uniform."""
    channels = np.asarray(channels, np.float32).copy()
    k = len(channels)
    lo, hi = lower(k), upper(k)
    seen_t = np.asarray(seen[: problem.num_texels], bool)
    n_seen = int(np.sum(seen_t))
    r, jac = linearization
    e_map = _energy(r, xs, problem)  # no prior here: the check is skipped with one
    sigma2 = residual_variance(e_map, 3 * num_pixels, n_seen * int(np.sum(channels)))
    xs = np.asarray(xs, np.float32)
    report, uniform = {}, {}
    precision = None  # per-texel precisions of the model as it stands (recomputed when a channel goes)
    for name, c in SELECTABLE:
        if channels[c] == 0:
            continue
        if precision is None:
            precision = texel_precisions(np.asarray(_normal_blocks(jac, problem)), channels > 0, seen_t)
        s = precision[seen_t, c]
        n_texels = int(np.sum(s > 0))  # the texels whose channel c the images constrain at all
        if n_texels < 2:
            report[name] = dict(uniform=False, texels=n_texels, skipped="fewer than two texels constrain it")
            continue
        threshold = 2.0 * (n_texels - 1)
        value = weighted_value(xs[seen_t, c], s, float(lo[c]), float(hi[c]))
        wald = wald_statistic(xs[seen_t, c], s, value, sigma2)
        entry = dict(texels=n_texels, threshold=threshold, wald=wald)
        if wald > WALD_MARGIN * threshold:
            report[name] = dict(entry, uniform=False)
            continue
        reduced_channels = channels.copy()
        reduced_channels[c] = 0.0
        free = (seen_t[:, None] * reduced_channels[None, :]).astype(np.float32)
        reduced = dataclasses.replace(problem, free=jax.device_put(free, problem.free.sharding))
        direction = jax.device_put(uniform_direction(seen_t, c, k)[None], problem.free.sharding)
        num_free = n_seen * int(np.sum(reduced_channels))
        x_red, steps, values, converged = xs, 0, [], False
        where["check"] = name
        for i in range(NEWTON_STEPS + 1):
            values.append(value)
            x_red = np.array(x_red, np.float32)
            x_red[seen_t, c] = value
            x_red, info = runner(to_device(x_red, np.float32), reduced, REFIT_STEPS, num_free)
            steps += info["steps"]
            r_red, jac_red = runner.linearization
            if i == NEWTON_STEPS:
                break
            p, g = profile_hessian(r_red, jac_red, to_device(x_red, np.float32), reduced, direction)
            curvature, slope = float(np.asarray(p)[0, 0]), float(np.asarray(g)[0])
            new = newton_value(value, slope, curvature, float(lo[c]), float(hi[c]))
            converged = curvature > 0 and abs(new - value) <= NEWTON_TOL * math.sqrt(sigma2 / curvature)
            if converged or not curvature > 0:
                break
            value = new
        where.pop("check")
        e_uniform = _energy(r_red, x_red, reduced)
        statistic = aic_statistic(e_uniform, e_map, sigma2)
        keep = prefers_uniform(statistic, n_texels)
        report[name] = dict(entry, uniform=keep, statistic=statistic, value=value, steps=steps, values=values,
                            converged=converged)
        if keep:
            xs, linearization, problem, e_map = np.asarray(x_red, np.float32), (r_red, jac_red), reduced, e_uniform
            jac, channels, precision = jac_red, reduced_channels, None
            uniform[c] = value
    return xs, linearization, problem, report, uniform


def _neighbour_weights(shape, seen, size: int, on: bool):
    """The smoothness prior's neighbour pairs at this resolution, padded to `size`, and their
    weights: 1 where both texels are seen, else 0 (all 0 when the prior is not `on`)."""
    pairs = np.zeros((size, 2), np.int32)
    weights = np.zeros(size, np.float32)
    if on:
        p = neighbour_pairs(shape)
        pairs[: len(p)] = p
        weights[: len(p)] = (seen[p[:, 0]] & seen[p[:, 1]]).astype(np.float32)
    return pairs, weights


def _finish_level(runner, problem: Problem, x, info, steps: int, num_free: int, settle_weight=None):
    """A level's last `steps` on `problem` from x: the first `SETTLE_STEPS` under the prior
    weight `settle_weight` (unless None), the rest as asked; (x, info, linearisation)."""
    if settle_weight is not None:
        x, info = _merge(info, runner(to_device(x, np.float32), with_smooth(problem, settle_weight), SETTLE_STEPS,
                                      num_free))
        steps -= SETTLE_STEPS
    x, info = _merge(info, runner(to_device(x, np.float32), problem, steps, num_free))
    return x, info, runner.linearization


def _centres_explain_better(energies) -> bool:
    """Of (samples' data term, centres' data term, ...): the centres explain the images at
    least as well (ties go to the cheaper model)."""
    return energies[1] <= energies[0]


def _samples_side(obs: Observations) -> int:
    """n of the n × n samples per pixel of `obs`."""
    return int(round(math.sqrt(obs.samples)))


def _final_residuals(x, problem: Problem, linearization):
    """Pixel residuals at a solver's result: from its linearisation (the structured solver),
    else evaluated (the optimistix solvers return none)."""
    if linearization is not None:
        return linearization[0]
    return jax.jit(pixel_residuals)(to_device(x, np.float32), problem)


def footprint_energies(obs: Observations, residuals, centres: Observations, centre_residuals):
    """The data terms 1/2 Σ_p ||r̃_p||² (the loss: r̃ is the residual transformed by the robust
    loss, the residual itself for l2) of two fits of the same images, one with pixel samples
    (`obs`) and one at pixel centres, summed over the pixels both use (a pixel is usable with
    samples only where all of them hit the mesh): (samples' energy, centres' energy, pixels).
    Both models have the same maps to fit and no other parameter, so the lower energy is the
    likelier footprint (for l2 and Gaussian noise, the higher likelihood)."""

    def per_pixel(o: Observations, r):
        r = np.asarray(r, np.float64)[: o.num_pixels]
        view = np.asarray(o.pixel_rows(o.view_index)).astype(np.int64)
        pix = np.asarray(o.pixel_rows(o.pixel)).astype(np.int64)
        key = view * (1 << 40) + pix
        return key, 0.5 * np.sum(r * r, axis=1)

    ks, es = per_pixel(obs, residuals)
    kc, ec = per_pixel(centres, centre_residuals)
    common, i_s, i_c = np.intersect1d(ks, kc, assume_unique=True, return_indices=True)
    return float(np.sum(es[i_s])), float(np.sum(ec[i_c])), int(common.size)


def continuation_scale(jac, problem: Problem) -> float:
    """The data's mean curvature per fitted texel and channel, in base colour where it is fitted:
    the mean diagonal of the per-texel blocks of JᵀJ (`pbrfit.solvers.normal_blocks`) over the
    free base-colour channels (else over all free channels); 1 where nothing is free or the
    mean is not a positive number."""
    diag = np.diagonal(np.asarray(_normal_blocks(jac, problem)), axis1=1, axis2=2)
    free = np.asarray(problem.free) > 0
    cols = slice(0, 3) if free[:, :3].any() else slice(None)
    values = diag[:, cols][free[:, cols]]
    scale = float(np.mean(values)) if values.size else 1.0
    return scale if math.isfinite(scale) and scale > 0 else 1.0


def with_smooth(problem: Problem, weight: float) -> Problem:
    """`problem` with the smoothness prior's weight set to `weight` (placed like the old one)."""
    return dataclasses.replace(problem, smooth=jax.device_put(np.float32(weight), problem.smooth.sharding))


def _merge(info: Optional[dict], run) -> tuple:
    """(x, info) of a solver run, its counts added to those of the runs before it on this level."""
    x, more = run
    if info is not None:
        for count in ("steps", "accepted", "cg_iterations"):  # counts add up; the rest is the last run's
            if count in info:
                more[count] += info[count]
        if "search_moved" in info:
            more["search_moved"] = info["search_moved"]
    return x, more


class _Compiler:
    """Ahead-of-time compilation, timed apart from the runs, each executable compiled once per key.

    `prefetch` starts a compile in a background thread as soon as the arguments' shapes are
    known, so that it overlaps the work before its first use (compiling is mostly single-threaded,
    so a second core is idle meanwhile); `get` returns the executable, waiting for it if needed.
    The thread compiles under the caller's default device, matmul precision and x64 setting
    (JAX's contexts for them are thread-local). ``clock["compile"]`` gets the time the fit waits
    for compiles, ``clock["compile_background"]`` the compile time the thread spent while the fit
    did other work (its compile time less the wait)."""

    def __init__(self, clock: dict, background: bool = True):
        self.clock, self.background = clock, background
        self.clock.setdefault("compile", 0.0)
        self.executor = None
        self.pending, self.done = {}, {}

    def prefetch(self, key, fn, *args, **kwargs) -> None:
        if not self.background or key in self.pending or key in self.done:
            return
        if self.executor is None:
            self.executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pbrfit-compile")
        config = jax.config
        device, precision, x64 = (config.jax_default_device, config.jax_default_matmul_precision,
                                  config.jax_enable_x64)

        def work():
            with jax.default_device(device), jax.default_matmul_precision(precision), jax.enable_x64(x64):
                t0 = time.perf_counter()
                compiled = fn.lower(*args, **kwargs).compile()
                return compiled, time.perf_counter() - t0

        self.pending[key] = self.executor.submit(work)

    def get(self, key, fn, *args, **kwargs):
        if key in self.done:
            return self.done[key]
        t0 = time.perf_counter()
        future = self.pending.pop(key, None)
        if future is None:
            compiled = fn.lower(*args, **kwargs).compile()
        else:
            compiled, took = future.result()
            overlapped = max(took - (time.perf_counter() - t0), 0.0)
            self.clock["compile_background"] = self.clock.get("compile_background", 0.0) + overlapped
        self.clock["compile"] += time.perf_counter() - t0
        self.done[key] = compiled
        return compiled

    def close(self) -> None:
        """Stop: compiles not started are dropped; a running one finishes in its thread, unwaited."""
        if self.executor is not None:
            self.executor.shutdown(wait=False, cancel_futures=True)
            self.executor = None
        self.pending.clear()


def compile_summary(times: Mapping[str, float]) -> str:
    """A report's compile times in words: waited for, and compiled meanwhile in the background."""
    text = f"compile {times.get('compile', 0.0):.1f} s"
    if times.get("compile_background", 0.0) > 0.0:
        text += f", {times['compile_background']:.1f} s more overlapped"
    return text


def _problem_key(problem: Problem) -> tuple:
    """What an executable over `problem` is specialised to: rows per pixel and the shapes."""
    return (problem.obs.samples, tuple(problem.index.shape), tuple(problem.free.shape), tuple(problem.pairs.shape))


def _timed(compiler: _Compiler, key, fn, name: str, *args):
    """Run `fn` compiled ahead of time (`_Compiler.get`) and add the run time to ``clock[name]``."""
    compiled = compiler.get(key, fn, *args)
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    compiler.clock[name] = compiler.clock.get(name, 0.0) + time.perf_counter() - t0
    return out


class _Runner:
    """Runs a solver, compiled ahead of time once per problem shape (`_Compiler`): once per fit,
    or twice when the start runs on pixel centres (`fit_observations`); an optimistix solver
    also once per step budget (its loop length is static)."""

    def __init__(self, solver, rtol, atol, progress, compiler: _Compiler, cg_rtol: float = CG_RTOL):
        self.solver, self.rtol, self.atol, self.progress, self.compiler = solver, rtol, atol, progress, compiler
        self.cg_rtol = float(cg_rtol)
        self.clock = compiler.clock
        # an optimistix solver reports each evaluation of the objective, numbered here from 0 in
        # every run (one lambda per runner: the compiled solve keeps the one it was traced with)
        self.evaluations = itertools.count()
        self.tick = None if progress is None else (lambda value: progress(next(self.evaluations), value))

    def _call(self, x0, problem, steps, num_free):
        """(key, fn, args, kwargs, optimistix solver or None) of a run."""
        if self.solver == DEFAULT_SOLVER:
            args = (x0, problem, to_device(steps, np.int32), self.rtol, self.atol)
            # cg_rtol as an array: one executable serves every tolerance
            kwargs = dict(cg_rtol=to_device(self.cg_rtol, np.float32), progress=self.progress)
            return ("structured",) + _problem_key(problem), structured_lm, args, kwargs, None
        opt, is_ls = make_solver(self.solver, self.rtol, self.atol, num_free)
        key = (type(opt).__name__, steps) + _problem_key(problem)
        return key, optx_solve, (x0, problem, opt, is_ls, steps, self.tick), {}, opt

    def prefetch(self, x0, problem, num_free) -> None:
        """Start compiling the structured solver for `problem` in the background (its step
        budget is an argument; an optimistix solver's is not known yet, so it is not)."""
        if self.solver == DEFAULT_SOLVER:
            key, fn, args, kwargs, _ = self._call(x0, problem, 0, num_free)
            self.compiler.prefetch(key, fn, *args, **kwargs)

    def __call__(self, x0, problem, steps, num_free):
        self.evaluations = itertools.count()
        key, fn, args, kwargs, opt = self._call(x0, problem, steps, num_free)
        compiled = self.compiler.get(key, fn, *args, **kwargs)
        t0 = time.perf_counter()
        out = compiled(*args, **kwargs)
        x = np.asarray(jax.block_until_ready(out[0]))
        self.clock["solve"] += time.perf_counter() - t0
        if opt is None:
            s = out[1]
            info = dict(steps=int(s.steps), accepted=int(s.accepted), cg_iterations=int(s.cg_iterations))
            self.linearization = (out[2], out[3])
        else:
            info = dict(steps=int(out[1]), result=int(out[2]), method=type(opt).__name__)
            self.linearization = None
        return x, info

    def jacobian(self, x, problem, num_free):
        """Per-pixel Jacobians (P, 3, K) at x: the structured solver's step 0, which only
        linearises (compiled already for the solve)."""
        self(x, problem, 0, num_free)
        return self.linearization[1]


def _finish(obs, problem, x, final, channels, seen, model, solver, history, loss, smooth, times, t_post, t_start,
            linearization=None, wrap: str = "repeat", uniform: Optional[Mapping] = None,
            uncertainty_radius: int = WINDOW_RADIUS):
    """The result at the fit's x. The maps' standard errors come from each texel's window of
    ``uncertainty_radius`` (`pbrfit.uncertainty.window_standard_errors`; 0: its own block), with
    the channels that sit on a bound held for the others' errors.
    ``uniform`` {channel: value}: channels fitted as one common value (`_uniform_check`); their
    standard errors, at every seen texel, are σ̂ sqrt(diag(P⁻¹)) for P their profile curvature
    matrix (`pbrfit.selection.profile_hessian`)."""
    uniform = dict(uniform or {})
    k = len(channels)
    texel_channels = np.asarray(channels, np.float32).copy()
    texel_channels[list(uniform)] = 0.0
    xj = to_device(x.reshape(-1, k), np.float32)
    if linearization is None:
        r, jac, energy = jax.jit(linearize)(xj, problem)
    else:
        r, jac = linearization
        # (numpy: an eager jnp reduction would compile kernels of its own)
        with np.errstate(over="ignore"):  # (float32, as the solve sums it: an overflow is refused by `fit`)
            energy = (jax.jit(objective)(xj, problem) if float(problem.smooth) > 0
                      else 0.5 * np.sum(np.square(np.asarray(r))))
    blocks = np.asarray(_normal_blocks(jac, problem))
    n_res = 3 * obs.num_pixels
    n_par = int(np.sum(seen)) * int(np.sum(texel_channels)) + len(uniform)
    sigma2 = residual_variance(float(energy), n_res, n_par)
    radius = max(window_radii(tuple(final), uncertainty_radius))
    couplings = np.asarray(_neighbour_blocks(jac, problem, tuple(final))) if radius > 0 else None
    xt = np.asarray(x, np.float32).reshape(-1, k)
    pinned = (xt <= lower(k)) | (xt >= upper(k))  # on a bound: the projected solver holds them
    sigma = window_standard_errors(blocks, couplings, tuple(final), texel_channels > 0, seen, sigma2, radius, pinned)
    if uniform:
        cs = sorted(uniform)
        directions = np.stack([uniform_direction(seen, c, k) for c in cs])
        p = np.asarray(profile_hessian(r, jac, xj, problem, jax.device_put(directions, problem.free.sharding))[0],
                       np.float64)
        if np.all(np.linalg.eigvalsh(p) > 0):
            var = np.diag(np.linalg.inv(p))
        else:  # a degenerate pair: each value's σ with the other held
            d = np.diag(p)
            var = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), np.inf)
        for c, v in zip(cs, var):
            sigma[:, c] = np.where(seen, math.sqrt(sigma2 * v) if np.isfinite(v) else np.inf, np.inf)
    sigma = sigma.reshape(final + (k,))
    coverage = coverage_counts(_layout(obs, final, wrap), obs.samples)
    # Per-view renders in image space and PSNR (peak 1: display values).
    if loss == "l2":
        resid = np.asarray(r)[: obs.num_pixels]
    else:
        plain = dataclasses.replace(problem, loss="l2")
        resid = np.asarray(jax.jit(pixel_residuals)(xj, plain))[: obs.num_pixels]
    resid = resid / np.asarray(obs.pixel_rows(obs.residual_weight))  # image units (weights are > 0)
    target = np.asarray(obs.pixel_rows(obs.target))
    values = resid + target
    vidx = np.asarray(obs.pixel_rows(obs.view_index))
    pix = np.asarray(obs.pixel_rows(obs.pixel))
    images, targets, masks, psnr = [], [], [], []
    for view, (h, w) in enumerate(obs.shapes):
        sel = vidx == view
        img = np.zeros((h * w, 3), np.float32)
        tgt = np.zeros((h * w, 3), np.float32)
        msk = np.zeros(h * w, bool)
        img[pix[sel]] = values[sel]
        tgt[pix[sel]] = target[sel]
        msk[pix[sel]] = True
        images.append(img.reshape(h, w, 3))
        targets.append(tgt.reshape(h, w, 3))
        masks.append(msk.reshape(h, w))
        with np.errstate(over="ignore", invalid="ignore"):  # (an overflowed fit: refused by `fit`)
            mse = float(np.mean(np.square(resid[sel], dtype=np.float64))) if sel.any() else float("nan")
        psnr.append(float("inf") if mse == 0 else -10.0 * math.log10(mse) if 0 < mse < math.inf
                    else float("-inf") if mse == math.inf else float("nan"))
    normal = normal_from_slopes(to_device(x[..., 5:7], np.float32)) if k > 5 else None
    material = Material(base_color=to_device(x[..., 0:3], np.float32), metallic=to_device(x[..., 3:4], np.float32),
                        roughness=to_device(x[..., 4:5], np.float32), normal=normal)
    times = dict(times, post=time.perf_counter() - t_post)
    report = dict(
        model=model.describe(),
        solver=solver,
        loss=loss,
        smooth=smooth,
        resolution=list(final),
        fitted=[c for c, m in zip(CHANNELS + NORMAL_CHANNELS, channels) if m > 0],
        levels=history,
        steps=int(sum(h["steps"] for h in history)),
        final_loss=float(energy),
        residual_sigma=math.sqrt(sigma2),
        pixels=int(obs.num_pixels),
        pixel_samples=_samples_side(obs),
        observed_texels=int(np.sum(coverage > 0)),
        psnr=psnr,
        times={name: float(v) for name, v in times.items()},
        wall_time=float(times["setup"] + time.perf_counter() - t_start),
        devices=sorted(str(d) for d in problem.obs.target.sharding.device_set),
        uncertainty=dict(radius=int(uncertainty_radius), window=[2 * r + 1 for r in window_radii(tuple(final),
                                                                                               uncertainty_radius)]),
    )
    if tuple(final) == (1, 1):  # a uniform material: the five numbers and their standard errors
        report["material"] = dict(base_color=[float(v) for v in x[0, 0, 0:3]], metallic=float(x[0, 0, 3]),
                                  roughness=float(x[0, 0, 4]))
        report["material_sigma"] = dict(base_color=[float(v) for v in sigma[0, 0, 0:3]],
                                        metallic=float(sigma[0, 0, 3]), roughness=float(sigma[0, 0, 4]))
    return FitResult(material, sigma, coverage, report, images, targets, masks)


def _display_referred(capture) -> bool:
    """Whether any frame holds display values: sRGB-encoded, or tone mapped."""
    return (getattr(capture, "tonemap", "none") != "none"
            or any(f.color_space == "srgb" for f in getattr(capture, "frames", ())))


def _image_pixels(capture) -> int:
    """Pixels of all frames together."""
    return int(sum(f.image.shape[0] * f.image.shape[1] for f in getattr(capture, "frames", ())))


def footprint_choice(capture, pixel_samples="auto", views=None) -> tuple[int, bool, Optional[str]]:
    """(n, select, skipped) for `fit`'s ``pixel_samples``: an integer n is taken as given;
    ``"auto"`` gives (`AUTO_PIXEL_SAMPLES`, True) for display-referred images (any frame in
    sRGB, or a tone map), which are photographs or finished renders and so usually pixel
    averages, and (1, False) for linear HDR images, where the cost (about three times the run
    time) is not paid unless asked for, although antialiased HDR renders average pixels too; for
    precomputed `views`, which hold pixel centres; and for display-referred captures of more than
    `AUTO_MAX_PIXELS` pixels, for which `skipped` says so (else None). select says to fit both
    footprints and keep the one that explains the images better (`fit_observations`)."""
    if not isinstance(pixel_samples, str):
        return pixel_samples, False, None
    if pixel_samples != "auto":
        raise ValueError(f"pixel_samples must be 'auto' or an integer from 1 to {MAX_PIXEL_SAMPLES}, "
                         f"got {pixel_samples!r}")
    if not _display_referred(capture) or views is not None:
        return 1, False, None
    pixels = _image_pixels(capture)
    if pixels > AUTO_MAX_PIXELS:
        return 1, False, (f"{pixels:,} image pixels > AUTO_MAX_PIXELS ({AUTO_MAX_PIXELS:,}): pixel centres only; "
                          f"--pixel-samples 2 fits the footprint")
    return AUTO_PIXEL_SAMPLES, True, None


def fit(capture, *, model: Optional[Model] = None, cache_dir=None, views=None, ibl: Optional[str] = None,
        pixel_ibl_settings: PixelIBLSettings = PixelIBLSettings(), pixel_samples="auto", **kwargs) -> FitResult:
    """Fit material maps to a `pbrfit.scene.Capture` (or the capture folder, read with
    `pbrfit.scene.load_capture`).

    Keyword arguments (all optional):
        cache_dir: a folder for the G-buffers (and per-pixel IBL integrals) computed from the
            capture, read back by later fits of the same capture and settings; default None: none
            kept (the command line's ``--cache``).
        views: precomputed `pbrfit.render.ViewInputs`, one per frame in the capture's order (as
            `pbrfit.views.capture_views` makes them), instead of those computed from the capture.
        pixel_samples: n: shade n × n samples per pixel and compare their mean radiance with the
            pixel (`pbrfit.observations`, pixel footprints): the model of an antialiased or
            supersampled capture (1: pixel centres). The grid start, the continuation's first
            steps and the search run on pixel centres, the settling and released steps on the
            samples (`fit_observations`). ``"auto"`` (default, `footprint_choice`): pixel
            centres for linear HDR images (and with precomputed ``views``); for display-referred
            ones (sRGB, tone mapped) the last steps run both ways, at centres and with 2 × 2
            samples (these stop after `PROBE_STEPS` when they do not yet match better), and the
            fit whose images match better is kept (the report's "footprint" entry gives both
            energies, and each fit's step count, the shared start's included).
        ibl: how the capture's environment light is integrated, ``"split_sum"`` (default: Karis
            2013, the renderer's tables) or ``"per_pixel"`` (`pbrfit.pixel_ibl`: each pixel's
            lobe integrals by Monte Carlo on a roughness grid, once before the solve, with
            ``pixel_ibl_settings``, cached in ``cache_dir`` like the G-buffers; no split-sum
            error, not with fitted normals). Ignored without an environment.
        resolution: map size N (or (H, W)); default `default_resolution(capture)`.
        fit: which maps are free, some of "base_color", "metallic", "roughness", "normal" (a
            tangent-space normal map, `pbrfit.parameters`; needs the mesh's tangents: uv);
            default: the three material maps, less those ``fixed`` holds (`fit_arguments`).
        fixed: values of maps held fixed, in [0, 1]: {"roughness": 0.4, "base_color": (H, W, 3)
            array, ...}; maps neither fitted nor given stay at `pbrfit.parameters.PRIOR`.
        maps: "texture" (maps) or "none" (one uniform material, 1 × 1 maps).
        solver: one of `SOLVERS`; max_steps (final level), coarse_steps, rtol, atol.
        cg_rtol: the structured solver's conjugate-gradient tolerance per step (in (0, 1),
            default `pbrfit.solvers.CG_RTOL`): looser takes fewer CG iterations per step.
        loss: "l2", "huber" or "cauchy" (scale `loss_scale`, image units); smooth: weight of the
            neighbour-difference prior (0 = off).
        coarse_to_fine: run the levels of `schedule`, or (default) the final resolution only.
        init: "grid" (`pbrfit.initialisation.grid_initialise`, default) or "prior" (start at PRIOR).
        search: after `SEARCH_AFTER` steps of the final level, re-search each texel's metallic and
            roughness with its neighbours fixed (`pbrfit.initialisation.coordinate_search`), then
            finish the steps: repairs texels left in a wrong roughness basin (default on).
        continuation: weights of a smoothness prior for the final level's first `SEARCH_AFTER`
            steps (added to ``smooth``), split evenly, relative to the data's curvature
            (`continuation_scale`), and the last one for `SETTLE_STEPS` after the search; the
            steps after them (at least `RELEASED_STEPS`, else no continuation) solve the
            objective as asked, so the prior only chooses basins (default `CONTINUATION`; () =
            off; structured solver only). The report's "continuation" entry gives the absolute
            weights and the step budgets used (None: none ran).
        uniform_check: after the solve, test whether metallic, then roughness, is better fitted as
            one common value than as a map (`pbrfit.selection`: Akaike's criterion on the data
            term, the common value re-fitted with the other maps): where the images cannot tell
            the channel's texels apart, the map fits noise and drags the maps correlated with it
            (base colour with metallic) along. Default on; structured solver, l2 loss and no
            ``smooth`` only (else the report says why it was skipped). The report's
            "uniform_check" entry gives each test's statistic, threshold and outcome; a uniform
            channel holds the value at every seen texel (unseen ones keep the prior) and its
            uncertainty the value's standard error. Its re-fits add up to
            (`NEWTON_STEPS` + 1) × `REFIT_STEPS` steps per channel, counted in the report's
            "steps" (a rejected test's too).
        repair: after the solve and before the uniform check, find the well-determined texels
            whose pixels fit worse than the noise explains (a cluster of neighbours left in a
            wrong basin, making up for each other), copy into them the nearest well-fitted
            texel's values, re-search and re-solve them and their neighbours with every other
            texel held (`pbrfit.repair`), and keep each cluster whose pixels fit better where the
            objective then falls; then once more for the texels out of line with their
            neighbours. Default on; structured solver only. Each pass adds
            `pbrfit.repair.REPAIR_STEPS` steps, counted in the report's "steps"; the report's
            "repair" entry gives each pass's kind ("misfit" or "outliers"), flagged and moved
            texels, clusters and texels kept, objective before and after, and whether it was
            kept.
        uncertainty_radius: the standard errors of ``uncertainty`` are each texel's with the
            (2 r + 1)² texels around it free as well, from the normal matrix's blocks
            (`pbrfit.uncertainty.window_standard_errors`): 0 takes the texel's own block alone
            (its neighbours held: optimistic, pixels read four texels at once), default
            `pbrfit.uncertainty.WINDOW_RADIUS` (1), at most `MAX_UNCERTAINTY_RADIUS`. The
            report's "uncertainty" entry gives the radius and the window used.
        devices: a sequence of JAX devices to split the pixels over (`pbrfit.sharding`); default
            None: the default device.
        noise_level: "uniform" (default: every residual weighs alike, the likeliest fit where
            the noise does not depend on the value) or "estimated" (`pbrfit.noise`: the first
            fit's residuals give the noise level as a function of the value, σ(v), and a second
            fit, started from the first, weighs each residual by σ_ref / σ(v̂) at the first
            fit's value, σ_ref the median level; for noise that grows with the signal, at 1.1 to
            1.5 times the cost). The report's "noise_level" entry gives the mode, and for
            "estimated" the level function and the first fit's steps and loss; "final_loss" and
            "residual_sigma" are then the weighted residuals' (in units of σ_ref), the PSNR the
            images'.
        model: override the `Model` (default `model_for_capture`: the one that rendered the images).
        background_compile: compile the structured solver and the search for each problem in a
            background thread as soon as their shapes are known, overlapping the grid start and
            the steps before their first use (default on; the report's ``times["compile"]`` is
            the time the fit waited for compiles, ``times["compile_background"]`` what was
            compiled meanwhile). Off: every compile runs where it is first needed.
        progress: called with {stage: "ibl", done, total} (pixels) while per-pixel IBL integrals
            are computed, then with {level, resolution, step, loss} after each step (``check``:
            the channel, during the uniform check's re-fits; an optimistix
            solver's: at each evaluation of the objective, one per step; a host callback; leave
            None for a solve with no host round-trips).
    """
    t0 = time.perf_counter()
    # the arguments first: a wrong one is said at once, before the capture is read
    if ibl not in (None,) + IBL_MODES:
        raise ValueError(f"ibl must be one of {', '.join(IBL_MODES)}, got {ibl!r}")
    kwargs["fit"], kwargs["fixed"] = fit_arguments(kwargs.get("fit"), kwargs.get("fixed"))
    check_options(**{name: kwargs.get(name, default) for name, default in _OPTION_DEFAULTS.items()})
    _check_kinds(**{name: kwargs.get(name, default) for name, default in _KIND_DEFAULTS.items()})
    _check_names(noise_level=kwargs.get("noise_level", "uniform"), loss=kwargs.get("loss", "l2"),
                 init=kwargs.get("init", "grid"), wrap=kwargs.get("wrap", "repeat"), pixel_samples=pixel_samples)
    if model is not None:
        _check_model(model, kwargs["fit"])
    if isinstance(capture, (str, os.PathLike)):
        from .scene import load_capture

        capture = load_capture(capture, require_uv=kwargs.get("maps", "texture") == "texture"
                               or "normal" in kwargs["fit"])
    from .scene import Capture

    if not isinstance(capture, Capture):
        raise ValueError(f"capture: expected a pbrfit.scene.Capture or a capture folder, got {type(capture).__name__}")
    model = model_for_capture(capture, kwargs["fit"], kwargs["fixed"]) if model is None else model
    if model.ibl == "monte_carlo":
        raise ValueError("model: Model(ibl='monte_carlo') is the reference integrator, not a fit's shading; "
                         "use 'split_sum' or 'per_pixel'")
    from .views import check_environment

    check_environment(model, capture)
    if ibl is not None and model.ibl is not None:
        model = model.replace(ibl=ibl)
    _check_normals(model, kwargs["fit"])
    _check_brightness(capture)
    pixel_samples, select, skipped = footprint_choice(capture, pixel_samples, views)
    obs = observations_from_capture(capture, cache_dir=cache_dir, views=views, pixel_samples=pixel_samples)
    centres = None if obs.samples == 1 else observations_from_capture(capture, cache_dir=cache_dir, views=views)
    t_ibl = time.perf_counter()
    centre_tables = None
    if model.ibl == "per_pixel":
        from .views import capture_environment

        report = kwargs.get("progress")
        parts = [obs] if centres is None else [centres, obs]
        rows = np.cumsum([0] + [o.num_rows for o in parts])
        both = pixel_ibl(capture_environment(capture), np.concatenate([np.asarray(o.normal) for o in parts]),
                         np.concatenate([np.asarray(o.view) for o in parts]), model, pixel_ibl_settings,
                         cache_dir=cache_dir, progress=None if report is None else (
                             lambda done, total: report(dict(stage="ibl", done=done, total=total))))
        tables = dataclasses.replace(both, table=both.table[rows[-2]:])
        if centres is not None:
            centre_tables = dataclasses.replace(both, table=both.table[: rows[1]])
    else:
        tables = _ibl_for_capture(capture, model)
    t_ibl = time.perf_counter() - t_ibl
    result = fit_observations(obs, model=model, ibl=tables, setup_time=time.perf_counter() - t0, centres=centres,
                              centre_ibl=centre_tables, select_footprint=select, **kwargs)
    _check_finite(result, capture)
    if skipped is not None:
        result.report["footprint"] = dict(selected=1, skipped=skipped)
    if model.ibl is not None:
        result.report["ibl"] = dict(mode=model.ibl, seconds=t_ibl, **(
            dataclasses.asdict(pixel_ibl_settings) if model.ibl == "per_pixel" else {}))
    return result


def _brightest_pixel(capture) -> tuple[float, int, int, int]:
    """(|value|, frame, row, column) of the largest image value the fit may read (in a mask)."""
    best = (0.0, 0, 0, 0)
    for i, frame in enumerate(capture.frames):
        values = np.where(frame.mask[..., None], np.abs(frame.image), 0.0)
        if values.size and float(np.max(values)) > best[0]:
            row, col, _ = np.unravel_index(int(np.argmax(values)), values.shape)
            best = (float(values[row, col].max()), i, int(row), int(col))
    return best


def _check_brightness(capture) -> None:
    """`CaptureError` naming the frame and pixel where an image value is too bright for the float32
    solve: the sum of squared residuals over every pixel value would overflow float32 from that
    value alone, |v| > sqrt(float32 max / n), n the pixel values the fit may read."""
    n = 3 * max(sum(int(np.sum(f.mask)) for f in capture.frames), 1)
    limit = math.sqrt(float(np.finfo(np.float32).max) / n)
    value, i, row, col = _brightest_pixel(capture)
    if value > limit:
        raise CaptureError(
            f"{capture.frames[i].file_path}: frames[{i}]: pixel value {value:.3g} at row {row}, column {col} is "
            f"too bright for the float32 solve (squared and summed over the {n} pixel values it would "
            f"overflow; at most {limit:.3g}); mask it out or bring the images nearer 1")


def _check_finite(result: FitResult, capture) -> None:
    """`CaptureError` where the fit came out NaN or inf: every input is finite float32, but the
    solve squares and sums the residuals and their derivatives, so lights or an environment too
    bright for it (a light of 1e20 cd, an environment pixel of 1e30; too bright images are
    refused before the fit, `_check_brightness`) overflow it, and the maps or standard errors it
    writes would be NaN."""
    m = result.material
    bad = [name for name, values in (("base_color", m.base_color), ("metallic", m.metallic),
                                     ("roughness", m.roughness), ("normal", m.normal))
           if values is not None and not np.all(np.isfinite(np.asarray(values)))]
    seen = np.asarray(result.coverage) > 0
    if np.any(np.isnan(np.asarray(result.uncertainty)[..., :5][seen])):
        bad.append("uncertainty")
    if not math.isfinite(result.report.get("final_loss", 0.0)):
        bad.append("loss")
    if not bad:
        return
    value, k, _, _ = _brightest_pixel(capture)
    where = capture.json_path or capture.root
    raise CaptureError(
        f"{where}: the fit's {', '.join(bad)} came out NaN or beyond float32, as when the images or the light "
        f"they are rendered with are too bright for the float32 solve once squared (brightest image value "
        f"{value:.3g}, in frames[{k}] {Path(capture.frames[k].file_path).name}); bring them "
        "nearer 1 (the images' values, the lights' intensity, the environment's intensity or exposure)")


def map_rmse(truth: Material, result, coverage: Optional[np.ndarray] = None) -> dict:
    """Per-map RMSE of a fitted material (or `FitResult`) against the truth, over observed texels.

    The truth is resampled to the fitted resolution when sizes differ, as a held map is
    (`pbrfit.textures.resample_map`: block means for whole factors, else linear).
    """
    material = result.material if isinstance(result, FitResult) else result
    if coverage is None and isinstance(result, FitResult):
        coverage = result.coverage
    shape = material.resolution
    out = {}
    for name in ("base_color", "metallic", "roughness"):
        t = np.asarray(getattr(truth, name), np.float32)
        f = np.asarray(getattr(material, name), np.float32)
        if t.shape[:2] != shape:
            t = resample_map(t, shape)
        seen = np.ones(shape, bool) if coverage is None else np.asarray(coverage) > 0
        err = (f - t)[seen]
        out[name] = float(np.sqrt(np.mean(err ** 2))) if err.size else float("nan")
    return out


class _CallableModule(types.ModuleType):
    """`pbrfit.fit` is this module and the function: ``pbrfit.fit(capture)`` calls `fit`, and
    ``pbrfit.fit.fit_observations`` (or any other name here) is the module's. Python sets a
    package's attribute to a submodule when it is imported, so a plain alias of the function on the
    package would turn into this module on the first ``import pbrfit.fit``."""

    def __call__(self, *args, **kwargs) -> FitResult:
        return self.fit(*args, **kwargs)

    def __reduce__(self):  # pickled by name, like a function (process pools)
        return importlib.import_module, (self.__name__,)


__signature__ = inspect.signature(fit)  # what inspect.signature(pbrfit.fit) shows
sys.modules[__name__].__class__ = _CallableModule
