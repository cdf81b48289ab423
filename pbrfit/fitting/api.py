"""Fitting: recover glTF base colour, metallic and roughness maps from a capture.

`fit(capture, ...)` ray-casts the views once (`pbrfit.fitting.observations`), then minimises the squared
difference between the images and the renders of the maps, in the images' own space, with the
solver chosen by ``solver=``:

- ``"structured"`` (default): projected Levenberg-Marquardt on the exact image-space objective
  with per-pixel forward-mode Jacobians, block-sparse normal equations and block-Jacobi CG
  (`pbrfit.fitting.solvers.structured`), started by a per-texel grid search, then a continuation (the first steps
  under a smoothness prior of falling weight, released before the end), midway re-searching each
  texel's metallic and roughness with its neighbours fixed (`pbrfit.fitting.initialisation`); optionally
  coarse to fine (a uniform material first, then maps of growing resolution).
  `experiments/solvers.md` has the numbers that chose it.
- ``"lm"``, ``"gn"``, ``"dogleg"``, ``"bfgs"``, ``"lbfgs"``, ``"ncg"``, ``"adam"``: optimistix
  solvers on the same objective (`pbrfit.fitting.solvers.optx`), run through the same schedule.

After the structured solve, a repair (``repair=True``) starts texels whose pixels fit worse than
the noise explains, then texels out of line with their neighbours, again from their neighbours
(`pbrfit.fitting.stages.repair`), and the uniform check
(``uniform_check=True``) makes metallic, then roughness, one common value where Akaike's
criterion finds no support for a map in the images (`pbrfit.fitting.stages.selection`). Last, a texel whose
roughness the images do not constrain (its standard error above ``unconstrained_sigma``) is
held at the prior's 0.5, its base colour re-fitted (`pbrfit.fitting.stages.unconstrained`).

A pixel's footprint: a display-referred capture (sRGB, tone mapped) is fitted both at pixel
centres and with 2 × 2 samples per pixel, and the fit whose images match better is kept
(``pixel_samples="auto"``, `footprint_choice`); linear images are fitted at pixel centres, and
both ways, with 3 × 3 samples, only where the centres' residuals follow the blur of a box
footprint (`pbrfit.fitting.stages.footprint.footprint_evidence`).

The environment's light: the split sum, and per-pixel integrals with the mesh's occlusion where
the split sum's residuals show light it cannot model (``ibl="auto"``, `pbrfit.fitting.stages.ibl`);
that choice comes first, and the footprint's test runs on the light model kept.

The images' noise: plain least squares by default (``noise_level="uniform"``); with
``noise_level="estimated"`` a second fit weighs each residual by the inverse of the noise
level the first fit's residuals show at its value (`pbrfit.fitting.noise`): for shot noise, or noise
proportional to the signal.

Pixels can be split over several devices (``devices=``, `pbrfit.fitting.sharding`). The result carries
the maps, per-texel standard errors (`pbrfit.fitting.uncertainty`), per-texel coverage, the fitted
renders of every view and a report.

This module is the API. The options and their checks are `pbrfit.fitting.options`, one pass over
the levels is `pbrfit.fitting.passes` (its solver runs `pbrfit.fitting.runner`), the map size
`pbrfit.fitting.resolution`, the pixel footprint `pbrfit.fitting.stages.footprint`, and the result and its report
`pbrfit.fitting.result`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
import warnings
from pathlib import Path
from typing import Mapping, Optional

import numpy as np

from ..errors import CaptureError, listed
from .options import IBL_MODES, FitOptions, check_model, check_normals, held_report, occlusion_mode, options_from
from .passes import PassInputs, fit_pass
from .runner import PendingTables
from .result import FitResult, closed_times, map_rmse
from .stages.footprint import (AUTO_LINEAR_PIXEL_SAMPLES, box_plausible, footprint_choice, footprint_evidence,
                               probes_footprint)
from ..physics.model import Model
from .noise import estimate_noise_level
from .observations import Observations, linear_radiance, observations_from_capture, row_geometry
from ..lighting.ibl import OccludedTables
from ..lighting.pixel_ibl import per_row, pixel_ibl_parts, with_bounce
from ..lighting.visibility import Bounce, Visibility, blocked_cells, split_sum_factors
from ..render.views import capture_environment, capture_ibl, check_environment, environment_is_dark
from ..render.views import model_for_capture
from ..scene.capture import Capture, load_capture
from ..scene.occlusion import blocked_hits, cast_visibility, observed_radiance_at, occluding_faces, probe_share
from .resolution import default_resolution, schedule
from .solvers.names import DEFAULT_SOLVER, SOLVERS
from .stages.ibl import (bounce_explains_better, fit_sigma, misfit_evidence, per_pixel_explains_better,
                         per_pixel_skipped, split_sum_misfits)
from .stages.selection import uniform_channels
from ..transfer import to_device

__all__ = ["fit", "fit_observations", "FitResult", "default_resolution", "map_rmse", "fit_model", "SOLVERS",
           "DEFAULT_SOLVER", "IBL_MODES", "schedule", "footprint_choice", "uniform_channels"]


def fit_model(capture, options: FitOptions) -> Model:
    """The model a fit shades with: ``options.model`` where it is a `Model`; else the one the
    capture requires (`pbrfit.render.views.model_for_capture`: split-sum IBL when there is an
    environment; the metal lobe only when metallic is fitted or held at something nonzero), with
    the fields a mapping ``options.model`` gives changed."""
    if isinstance(options.model, Model):
        return options.model
    held_metal = np.any(np.asarray(options.held.get("metallic", 0.0)) != 0)
    changes = dict(metallic="metallic" in options.fitted or bool(held_metal), **(options.model or {}))
    model = model_for_capture(capture, **changes)
    check_model(model, options.fitted)
    return model


def _ibl_for_capture(capture, model: Model, environment=None):
    if model.ibl is None and not model.multiscatter:
        return None
    return capture_ibl(capture, model=model, environment=environment)


def _environment_visibility(capture, env, parts, options: FitOptions, model: Model, cache_dir):
    """The environment's visibility from the rows of ``parts`` (observations of ``capture``, in
    order) as ``options.occlusion`` asks, or by default as ``model``'s light model needs
    (`pbrfit.fitting.options.occlusion_mode`): (`pbrfit.lighting.visibility.Visibility` or None,
    its direction cells or None, the light its blocked directions bring or None (`Bounce`: with
    per-pixel integrals, unless ``occlusion_settings.bounce`` is "off"), the report's "occlusion"
    entry). "auto" casts nothing where no face has the mesh above it
    (`pbrfit.scene.occlusion.occluding_faces`), then probes a few points
    (`pbrfit.scene.occlusion.probe_share`) and goes on only where the mesh blocks at least
    ``options.occlusion_settings.auto_share`` of their irradiance."""
    start = time.perf_counter()
    settings = options.occlusion_settings
    mode = occlusion_mode(options.occlusion, model.ibl)
    entry = dict(mode=mode, used=False)
    done = lambda **more: dict(entry, **more, seconds=time.perf_counter() - start)  # noqa: E731
    if mode == "off":
        return None, None, None, done()
    if mode == "auto" and not occluding_faces(capture.mesh).any():
        return None, None, None, done(reason="no face has the mesh above it")
    geometry = [row_geometry(capture, o, cache_dir) for o in parts]
    points, normals = (np.concatenate([g[k] for g in geometry]) for k in (0, 1))
    if mode == "auto":
        entry["probed_share"] = probe_share(capture.mesh, env, points, normals, settings, cache_dir)
        if entry["probed_share"] < settings.auto_share:
            return None, None, None, done(reason=f"the mesh blocks less than auto_share {settings.auto_share:g} of the "
                                           "irradiance at the probed points")
    visibility, cells = cast_visibility(capture.mesh, env, points, normals, settings, cache_dir)
    bounce = None
    if settings.bounce != "off" and model.ibl == "per_pixel":
        bounce, entry["bounce"] = _observed_bounce(capture, parts[0], points, normals, visibility, cells, cache_dir,
                                                   settings.bounce)
    return visibility, cells, bounce, done(used=True, cells=cells.count, rows=len(points))


def _observed_bounce(capture, obs: Observations, points, normals, visibility: Visibility, cells, cache_dir,
                     options_bounce: str):
    """The light the blocked directions of ``visibility`` bring (`pbrfit.lighting.visibility`'s
    module docstring): where each blocked ray lands (`pbrfit.scene.occlusion.blocked_hits`), and
    the radiance the rows of ``obs`` (the first rows of ``points``, ``normals``) saw nearest to it
    (`pbrfit.scene.occlusion.observed_radiance_at`). Returns the `Bounce` and the report's entry
    (its mode: ``options_bounce``)."""
    start = time.perf_counter()
    at, at_normals = blocked_hits(capture.mesh, points, normals, cells.directions, np.asarray(visibility.bits),
                                  cache_dir)
    seen = slice(0, obs.num_rows)
    radiance, unseen = observed_radiance_at(points[seen], normals[seen], np.asarray(linear_radiance(obs)), at,
                                            at_normals)
    rows, _ = blocked_cells(np.asarray(visibility.bits), cells.count)
    offsets = np.searchsorted(rows, np.arange(len(points) + 1)).astype(np.int64)
    entry = dict(mode=options_bounce, used=True, rays=len(at), missed=int(np.sum(~np.isfinite(at[:, 0]))),
                 unseen_hits=float(np.mean(unseen)) if len(at) else 0.0)
    if not np.any(radiance):  # no light to bring: nothing to fit both ways
        return None, dict(entry, used=False, reason="no blocked ray brings light",
                          seconds=time.perf_counter() - start)
    return Bounce(radiance, offsets), dict(entry, seconds=time.perf_counter() - start)


def fit_observations(obs: Observations, options: Optional[FitOptions] = None, *, model=None,
                     ibl=None, centres: Optional[Observations] = None, centre_ibl=None, select_footprint: bool = False,
                     setup_time: float = 0.0, **overrides) -> FitResult:
    """Fit maps to prepared `Observations` (see `fit` for the arguments).

    The light is the caller's to describe: ``model`` (else ``options.model``: a `Model`, or a
    mapping of the fields to change in the default one) and ``ibl`` must be those of the capture
    the observations come from (`fit` derives them: `fit_model`, and
    `pbrfit.render.views.capture_ibl` or `pbrfit.lighting.pixel_ibl.pixel_ibl`). The defaults, ``Model()`` and no
    tables, shade with the observations' punctual lights alone, so a capture lit by an
    environment is fitted as if that light were absent.

    With several samples per pixel in `obs`, `centres` (optional) holds the same capture's
    observations at pixel centres (and `centre_ibl` their IBL, when it is per pixel): the grid
    start, the continuation's first steps and the coordinate search then run on them, at a
    quarter of the cost or less, and only the settling and released steps on `obs`. With
    ``select_footprint`` as well, those last steps run on both, from the same point (centres
    first), and the fit whose data term is lower over the pixels both use is kept
    (`pbrfit.fitting.stages.footprint.footprint_energies`; both have the same parameters, so that is the
    likelier model of the pixels' footprint). With the structured solver the samples stop after
    their first `pbrfit.fitting.passes.PROBE_STEPS` when these do not yet fit better than the centres'
    whole finish. The report's "footprint" entry gives both energies, the steps and the choice."""
    options = options_from(options, overrides)
    model = options.model if model is None else model
    if model is None or isinstance(model, Mapping):  # the default model, with the fields given changed
        model = Model(**(model or {}))
    check_model(model, options.fitted)
    check_normals(model.ibl, options.fitted)
    inputs = PassInputs(model=model, ibl=ibl, centres=centres, centre_ibl=centre_ibl,
                        select_footprint=select_footprint, setup_time=setup_time)
    if options.noise_level == "uniform":
        result, _ = fit_pass(obs, options, inputs)
        result.report["noise_level"] = dict(mode="uniform")
    else:
        result = _fit_weighted(obs, options, inputs)
    result.report["iterations"] = result.report["steps"]  # the capture spec's word for them
    result.report["resumed"] = None if options.checkpoint is None else options.checkpoint.resumed()
    # what the caller held (before the model's own: a model without the metal lobe holds metallic 0)
    result.report["held"] = held_report([f for f in options.fitted if model.metallic or f != "metallic"], options.held)
    return result


def _fit_weighted(obs: Observations, options: FitOptions, inputs: PassInputs) -> FitResult:
    """``noise_level="estimated"`` (`pbrfit.fitting.noise`): a plain fit, the noise level function of its
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
    first, x = fit_pass(obs, options, inputs, shared)
    footprint = first.report.get("footprint")
    centres = inputs.centres
    kept = centres if (obs.samples > 1 and footprint is not None and footprint.get("selected") == 1) else obs
    values = _fitted_values(first, kept)
    target = np.asarray(kept.pixel_rows(kept.target))
    n_res = values.size
    uniform = len(uniform_channels(first.report))
    # as `pbrfit.fitting.result.finish` counts
    n_par = (len(first.report["fitted"]) - uniform) * first.report["observed_texels"] + uniform
    level = estimate_noise_level(values, values - target, dof_scale=n_res / max(n_res - n_par, 1))
    weights = np.repeat(level.weights(values), kept.samples, axis=0)
    weighted = dataclasses.replace(kept, residual_weight=to_device(weights, np.float32))
    shared["where"].clear()
    shared["where"]["weighted"] = True  # every step from here on reports it
    second_options = options.replace(coarse_to_fine=False, continuation=None, search=False, repair=False)
    centre_ibl = kept is centres and per_row(inputs.ibl)  # the centres' own integrals (or factors)
    second_inputs = PassInputs(model=inputs.model, ibl=inputs.centre_ibl if centre_ibl else inputs.ibl, start=x)
    second, _ = fit_pass(weighted, second_options, second_inputs, shared)
    report = second.report
    report["wall_time"] = float(inputs.setup_time + time.perf_counter() - t_start)
    report["times"] = closed_times(dict(report["times"], setup=float(inputs.setup_time),
                                        post=first.report["times"].get("post", 0.0) + report["times"].get("post", 0.0)),
                                   report["wall_time"])
    report["steps"] += first.report["steps"]
    if footprint is not None:
        report["footprint"] = footprint
    report["repair"] = first.report["repair"]  # (the second fit runs none)
    report["noise_level"] = dict(mode="estimated", **level.describe(), first_fit=dict(
        steps=first.report["steps"], final_loss=first.report["final_loss"],
        residual_sigma=first.report["residual_sigma"], psnr=first.report["psnr"], levels=first.report["levels"],
        continuation=first.report["continuation"]))
    return second


def _warn_unused_frames(capture, *observations: Optional[Observations]) -> None:
    """Warn, in one line, of the frames none of whose pixels enter the fit under any footprint it
    may choose (``observations``: the samples' and the centres'; each pixel masked out, saturated
    or off the mesh: a camera that looks away, a mask of zeros): they are left out."""
    index = np.concatenate([np.asarray(o.view_index) for o in observations if o is not None])
    counts = np.bincount(index[index >= 0], minlength=len(capture.frames))
    unused = [k for k, count in enumerate(counts[: len(capture.frames)]) if count == 0]
    if unused:
        named = listed(f"frames[{k}] ({capture.frames[k].file_path})" for k in unused)
        warnings.warn(f"{capture.json_path}: {named}: no usable pixel (each masked out, saturated or off the "
                      "mesh); left out of the fit", UserWarning, stacklevel=3)


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


def fit(capture, options: Optional[FitOptions] = None, *, views=None, **overrides) -> FitResult:
    """Fit material maps to a `pbrfit.scene.capture.Capture` (or the capture folder, read with
    `pbrfit.scene.capture.load_capture`), with ``options`` (a `FitOptions`, default
    ``FitOptions()``) and any of its fields given as keywords (``pbrfit.fit(capture,
    resolution=64)``): the options are checked before the capture is read. The options, the
    fields of `FitOptions`, are all optional:

    Other Parameters:
        cache_dir: a folder for the G-buffers (and per-pixel IBL integrals) computed from the
            capture, read back by later fits of the same capture and settings; default None: none
            kept (the command line's ``--cache``).
        views: precomputed `pbrfit.render.shade.ViewInputs`, one per frame in the capture's order (as
            `pbrfit.render.views.capture_views` makes them), instead of those computed from the capture.
        pixel_samples: n: shade n × n samples per pixel and compare their mean radiance with the
            pixel (`pbrfit.fitting.observations`, pixel footprints): the model of an antialiased or
            supersampled capture (1: pixel centres). The grid start, the continuation's first
            steps and the searches (the fit's and the repair's) run on pixel centres, the
            settling, released and repair steps on the samples (`fit_observations`).
            ``"auto"`` (default, `footprint_choice`): pixel centres with precomputed ``views``;
            for linear HDR images pixel centres, then both ways as below, with 3 × 3 samples
            (a path tracer's box is finer than 2 × 2's quadrature), only where the centres'
            residuals show a box's blur
            (`pbrfit.fitting.stages.footprint.footprint_evidence`, the report's
            "footprint" "evidence"); for display-referred
            ones (sRGB, tone mapped) the last steps run both ways, at centres and with 2 × 2
            samples (these stop after `pbrfit.fitting.passes.PROBE_STEPS` when they do not yet match better), and the
            fit whose images match better is kept (the report's "footprint" entry gives both
            energies, and each fit's step count, the shared start's included).
        ibl: how the capture's environment light is integrated: ``"split_sum"`` (Karis 2013, the
            renderer's tables), ``"per_pixel"`` (`pbrfit.lighting.pixel_ibl`: each pixel's lobe
            integrals by Monte Carlo on a roughness grid, once before the solve, with
            ``pixel_ibl_settings``, cached in ``cache_dir`` like the G-buffers; no split-sum
            error, not with fitted normals) or ``"auto"`` (default, `pbrfit.fitting.stages.ibl`):
            the split sum, then, where that fit's residuals are shared by neighbouring pixels
            beyond what noise shows (light the split sum cannot model: a path tracer's, a
            camera's), the same fit with per-pixel integrals, keeping the one whose residual σ is
            lower (the report's "ibl" "choice" gives the evidence and both σ; the fit not kept
            counts as ``times["ibl_probe"]``). "auto" keeps a `Model` the caller gave, the split
            sum where normals are fitted, and the split sum beyond
            `pbrfit.fitting.stages.ibl.AUTO_MAX_IBL_PIXELS` rows to integrate (the choice's
            "skipped" says so). Ignored without an environment.
        occlusion: whether the mesh blocks the environment's light from its own points
            (`pbrfit.lighting.visibility`): "on" casts a shadow ray per observed point and
            direction cell once, before the solve (cached in ``cache_dir``), and both IBL modes
            use it (the per-pixel integrals per sample direction, the split sum as per-point
            factors); "off" lets the whole environment reach every point; "auto" is "on" where a
            probe of a few points finds the mesh blocking at least
            ``occlusion_settings.auto_share`` of their irradiance (a convex mesh casts nothing).
            Default None: by the light model (`pbrfit.fitting.options.occlusion_mode`), "auto"
            with per-pixel integrals (the light of a path tracer, a camera or pbrfit's Monte Carlo
            reference, which the mesh shadows), "off" with the split sum (the model of pbrfit's
            own split-sum renders, which cast no shadows of the environment).
            The report's "occlusion" entry says which, why, and the time it took. Ignored
            without an environment. With per-pixel integrals, ``occlusion_settings.bounce``
            says whether a blocked direction brings the light the capture's pixels saw where it
            lands ("on"), none ("off"), or, by default ("auto"), whichever fit explains the images
            better (`pbrfit.fitting.stages.ibl.bounce_explains_better`; the entry's "bounce").
        resolution: map size N (or (H, W)); default `default_resolution(capture)`.
        fit: which maps are free, some of "base_color", "metallic", "roughness", "normal" (a
            tangent-space normal map, `pbrfit.fitting.parameters`; needs the mesh's tangents: uv);
            default: the three material maps, less those ``fixed`` holds (`fit_arguments`).
        fixed: values of maps held fixed, in [0, 1]: {"roughness": 0.4, "base_color": (H, W, 3)
            array, ...}; maps neither fitted nor given stay at `pbrfit.fitting.parameters.PRIOR`.
        maps: "texture" (maps) or "none" (one uniform material, 1 × 1 maps).
        solver: an optimistix solver (an `optx.AbstractLeastSquaresSolver` or `optx.AbstractMinimiser`;
            default `pbrfit.StructuredLM()`), or its name, one of `SOLVERS` (made by
            `pbrfit.fitting.solvers.names.solver_for`); max_steps (final level), coarse_steps.
        rtol, atol: the solver's stopping tolerances, when given (default: the solver's own,
            `pbrfit.fitting.solvers.structured.RTOL` and `ATOL` for a named one).
        cg_rtol: the structured solver's conjugate-gradient tolerance per step (in (0, 1),
            default `pbrfit.fitting.solvers.structured.CG_RTOL`): looser takes fewer CG iterations per step.
        noise_rtol: the structured solver's noise-relative stop (>= 0, default
            `pbrfit.fitting.defaults.NOISE_RTOL`; 0: off): it stops at an accepted step that gains
            less than noise_rtol · p σ̂² / 2, where the maps move by less than their noise.
        loss: "l2", "huber" or "cauchy" (scale `loss_scale`, image units); smooth: weight of the
            neighbour-difference prior (0 = off).
        coarse_to_fine: run the levels of `schedule`, or (default) the final resolution only.
        init: "grid" (`pbrfit.fitting.initialisation.grid_initialise`, default) or "prior" (start at PRIOR).
        search: after `SEARCH_AFTER` steps of the final level, re-search each texel's metallic and
            roughness with its neighbours fixed (`pbrfit.fitting.initialisation.coordinate_search`), then
            finish the steps: repairs texels left in a wrong roughness basin (default on). (The
            step counts named here and below are `pbrfit.fitting.passes`'s.)
        continuation: weights of a smoothness prior for the final level's first `SEARCH_AFTER`
            steps (added to ``smooth``), split evenly, relative to the data's curvature
            (`pbrfit.fitting.passes.continuation_scale`), and the last one for `SETTLE_STEPS` after the
            search; the steps after them (at least `RELEASED_STEPS`, else no continuation) solve
            the objective as asked, so the prior only chooses basins (default `CONTINUATION`; () =
            off; structured solver only). The report's "continuation" entry gives the absolute
            weights and the step budgets used (None: none ran).
        uniform_check: after the solve, test whether metallic, then roughness, is better fitted as
            one common value than as a map (`pbrfit.fitting.stages.selection`: Akaike's criterion on the data
            term, the common value re-fitted with the other maps): where the images cannot tell
            the channel's texels apart, the map fits noise and drags the maps correlated with it
            (base colour with metallic) along. Default on; structured solver, l2 loss and no
            ``smooth`` only (else the report says why it was skipped). The report's
            "uniform_check" entry gives each test's statistic, threshold and outcome; a uniform
            channel holds the value at every seen texel (unseen ones keep the prior) and its
            uncertainty the value's standard error. Its re-fits add up to
            (`pbrfit.fitting.stages.selection.NEWTON_STEPS` + 1) × `pbrfit.fitting.stages.selection.REFIT_STEPS` steps per channel,
            counted in the report's "steps" (a rejected test's too).
        repair: after the solve and before the uniform check, find the well-determined texels
            whose pixels fit worse than the noise explains (a cluster of neighbours left in a
            wrong basin, making up for each other), copy into them the nearest well-fitted
            texel's values, re-search and re-solve them and their neighbours with every other
            texel held (`pbrfit.fitting.stages.repair`), and keep each cluster whose pixels fit better where the
            objective then falls; then once more for the texels out of line with their
            neighbours. Default on; structured solver only. Each pass adds
            `pbrfit.fitting.stages.repair.REPAIR_STEPS` steps, counted in the report's "steps"; the report's
            "repair" entry gives each pass's kind ("misfit" or "outliers"), flagged and moved
            texels, clusters and texels kept, objective before and after, and whether it was
            kept.
        unconstrained_sigma: after the uniform check, a texel whose roughness standard error
            exceeds this is held at the prior's 0.5, and its base colour re-fitted with it
            held (`pbrfit.fitting.stages.unconstrained`: where no highlight reaches a texel, the fitted value is
            the noise's, often on a bound). Default `pbrfit.fitting.stages.unconstrained.UNCONSTRAINED_SIGMA`;
            ``math.inf``: none is held. Structured solver and no ``smooth`` only; the report's
            "unconstrained" entry gives the threshold, the texels held and the re-fit's steps
            (counted in "steps"). A held texel's σ in ``uncertainty`` is what the images give
            at 0.5 (above the threshold).
        uncertainty_radius: the standard errors of ``uncertainty`` are each texel's with the
            (2 r + 1)² texels around it free as well, from the normal matrix's blocks
            (`pbrfit.fitting.uncertainty.window_standard_errors`): 0 takes the texel's own block alone
            (its neighbours held: optimistic, pixels read four texels at once), default
            `pbrfit.fitting.uncertainty.WINDOW_RADIUS` (1), at most `pbrfit.fitting.uncertainty.MAX_UNCERTAINTY_RADIUS`. The
            report's "uncertainty" entry gives the radius and the window used.
        devices: a sequence of JAX devices to split the pixels over (`pbrfit.fitting.sharding`); default
            None: the default device.
        noise_level: "uniform" (default: every residual weighs alike, the likeliest fit where
            the noise does not depend on the value) or "estimated" (`pbrfit.fitting.noise`: the first
            fit's residuals give the noise level as a function of the value, σ(v), and a second
            fit, started from the first, weighs each residual by σ_ref / σ(v̂) at the first
            fit's value, σ_ref the median level; for noise that grows with the signal, at 1.1 to
            1.5 times the cost). The report's "noise_level" entry gives the mode, and for
            "estimated" the level function and the first fit's steps and loss; "final_loss" and
            "residual_sigma" are then the weighted residuals' (in units of σ_ref), the PSNR the
            images'.
        model: the `Model` (default `fit_model`: the one the capture requires), or a mapping of the
            fields to change in it (``{"diffuse": "burley"}``; the command line's ``--model``).
        background_compile: compile the structured solver and the search for each problem in a
            background thread as soon as their shapes are known, overlapping the grid start and
            the steps before their first use (default on; the report's ``times["compile"]`` is
            the time the fit waited for compiles, ``times["compile_background"]`` what was
            compiled meanwhile), and build the split sum's tables in a thread of their own
            while the grid start compiles (`pbrfit.fitting.runner.PendingTables`). Off: every
            compile runs where it is first needed, the tables before the fit.
        progress: called with {stage: "ibl", done, total} (pixels) while per-pixel IBL integrals
            are computed, then with {level, resolution, stage} as each stage begins ("grid
            start", "solving", "search", each stage after the solve that runs by its name,
            "standard errors") and {level, resolution, step, loss} for each step (``check``:
            the channel, during the uniform check's re-fits): the structured solver's after each
            solve (it keeps the losses in its state, so its program holds no host callback), with
            ``budget``, the most steps that solve may take (it stops sooner once converged); an
            optimistix solver's at each evaluation of the objective, one per step, by a host
            callback.
        checkpoint: a `pbrfit.fitting.checkpoint.Checkpoint`: each solver run is journaled in its
            folder, and the structured solver's state kept every few seconds, so that a fit
            interrupted (even killed) and run again with the same checkpoint (``resume=True``)
            replays what it had solved and goes on from there, to the same maps; the report's
            "resumed" entry says what was replayed and where the fit went on (None: started
            afresh). Default None: none kept.
        quality: the speed ladder's rung (`pbrfit.fitting.defaults.QUALITY`: "draft",
            "default", "best"), which sets the options it names that are not given.
    """
    t0 = time.perf_counter()
    options = options_from(options, overrides)  # checked at once, before the capture is read
    if isinstance(capture, (str, os.PathLike)):
        capture = load_capture(capture, require_uv=options.maps == "texture" or "normal" in options.fitted)
    if not isinstance(capture, Capture):
        raise ValueError(f"capture: expected a pbrfit.scene.capture.Capture or a capture folder, "
                         f"got {type(capture).__name__}")
    model = fit_model(capture, options)
    check_environment(model, capture)
    if options.ibl != "auto" and model.ibl is not None:
        model = model.replace(ibl=options.ibl)
    check_normals(model.ibl, options.fitted)
    _check_brightness(capture)
    pixel_samples, select, skipped = footprint_choice(capture, options.pixel_samples, views)
    result = _fit_footprint(capture, options, model, views, pixel_samples, select, t0)
    choice = None
    if _chooses_ibl(options, model):
        result, model, choice = _choose_light_model(capture, options, model, views, pixel_samples, select, result)
    if skipped is not None:
        result.report["footprint"] = dict(selected=1, skipped=skipped)
    elif probes_footprint(capture, options.pixel_samples, views):
        evidence = footprint_evidence(result.images, result.targets, result.masks)
        # (under per-pixel integrals chosen by "auto", the samples' integrals are capped as its own are)
        too_many = (per_pixel_skipped(_integral_rows(result, AUTO_LINEAR_PIXEL_SAMPLES, True))
                    if choice is not None and model.ibl == "per_pixel" else None)
        if box_plausible(evidence) and too_many is None:  # both footprints, the centres' fit spent on the test
            probe = result
            result = _fit_footprint(capture, _bounce_decided(options, probe), model, views, AUTO_LINEAR_PIXEL_SAMPLES,
                                    True, time.perf_counter())
            result = _spent_before(result, probe, "footprint_probe")
            _carry_bounce_choice(result, probe)
            result.report["footprint"]["evidence"] = evidence
        else:
            result.report["footprint"] = dict(selected=1, evidence=evidence)
            if box_plausible(evidence):
                result.report["footprint"]["skipped"] = too_many
    if choice is not None:
        result.report["ibl"]["choice"] = choice
    return result


def _choose_light_model(capture, options: FitOptions, model: Model, views, pixel_samples: int, select: bool,
                        result: FitResult) -> tuple[FitResult, Model, dict]:
    """``ibl="auto"`` after the split-sum ``result`` (`pbrfit.fitting.stages.ibl`): where its
    residuals show light the split sum cannot model, the same fit with per-pixel integrals (unless
    it has more rows to integrate than `pbrfit.fitting.stages.ibl.AUTO_MAX_IBL_PIXELS`), and of the
    two the fit of lower residual σ, with the other's time added. Returns (the fit kept, its
    model, the report's "ibl" "choice")."""
    evidence = misfit_evidence(result.images, result.targets, result.masks)
    misfits = split_sum_misfits(evidence)
    too_many = per_pixel_skipped(_integral_rows(result, pixel_samples, select)) if misfits else None
    choice = dict(evidence=evidence, tried=misfits and too_many is None)
    if too_many is not None:
        choice["skipped"] = too_many
    if not choice["tried"]:
        return result, model, choice
    other = _fit_footprint(capture, options, model.replace(ibl="per_pixel"), views, pixel_samples, select,
                           time.perf_counter())
    choice["residual_sigma"] = dict(split_sum=fit_sigma(result.report), per_pixel=fit_sigma(other.report))
    if per_pixel_explains_better(result.report, other.report):
        model, result, other = model.replace(ibl="per_pixel"), other, result
    return _spent_before(result, other, "ibl_probe"), model, choice


def _integral_rows(result: FitResult, samples: int, select: bool) -> int:
    """The rows per-pixel integrals take for the pixels ``result`` fitted, with ``samples`` ×
    ``samples`` samples per pixel, and their centres as well where ``select``."""
    return int(result.report["pixels"]) * (samples ** 2 + (1 if select else 0))


def _chooses_ibl(options: FitOptions, model: Model) -> bool:
    """Whether ``options.ibl`` "auto" chooses the model of the environment light
    (`pbrfit.fitting.stages.ibl`): where the capture has an environment the split sum shades, the
    model is the capture's (not one the caller gave, nor one whose ``ibl`` they set) and normals
    are not fitted (per-pixel integrals hold them fixed)."""
    given = isinstance(options.model, Model) or (isinstance(options.model, Mapping) and "ibl" in options.model)
    return (options.ibl == "auto" and model.ibl == "split_sum" and not given
            and "normal" not in options.fitted)


#: The report's times of fits a fit ran before the one it kept (`_spent_before`).
_PROBE_TIMES = ("ibl_probe", "footprint_probe", "bounce_probe")


def _bounce_decided(options: FitOptions, earlier: FitResult) -> FitOptions:
    """``options`` with ``occlusion_settings.bounce`` "auto" settled as ``earlier`` (a fit of the
    same capture that chose) kept it: a later fit (both footprints) does not fit both ways again."""
    entry = (earlier.report.get("occlusion") or {}).get("bounce") or {}
    if options.occlusion_settings.bounce != "auto" or "residual_sigma" not in entry:
        return options
    settings = dataclasses.replace(options.occlusion_settings, bounce="on" if entry["used"] else "off")
    return dataclasses.replace(options, occlusion_settings=settings)


def _carry_bounce_choice(result: FitResult, earlier: FitResult) -> None:
    """The bounce's choice made by ``earlier`` (`_bounce_decided`) in ``result``'s report."""
    chosen = (earlier.report.get("occlusion") or {}).get("bounce") or {}
    occlusion = result.report.get("occlusion")
    if "residual_sigma" in chosen and occlusion is not None and occlusion.get("used"):
        occlusion["bounce"] = dict(occlusion.get("bounce") or {}, mode="auto", used=chosen["used"],
                                   residual_sigma=chosen["residual_sigma"], chosen_by="footprint_probe")


def _spent_before(result: FitResult, earlier: FitResult, name: str) -> FitResult:
    """``result`` with the wall time of ``earlier``, a fit of the same capture run for a test or
    a choice and not kept, added: to its wall time, and to its times as ``name`` (what ``earlier``
    itself counted under `_PROBE_TIMES` keeps its name)."""
    before = earlier.report["times"]
    carried = {k: float(before[k]) for k in _PROBE_TIMES if k in before}
    times = dict(result.report["times"])
    for k, v in dict(carried, **{name: earlier.report["wall_time"] - sum(carried.values())}).items():
        times[k] = times.get(k, 0.0) + v
    result.report["times"] = times
    result.report["wall_time"] += earlier.report["wall_time"]
    return result


def _fit_footprint(capture, options: FitOptions, model: Model, views, pixel_samples: int, select: bool,
                   t0: float) -> FitResult:
    """`fit` with ``pixel_samples`` samples per pixel (``select``: and pixel centres, keeping the
    footprint that explains the images better), its setup timed from ``t0``."""
    cache_dir = options.cache_dir
    obs = observations_from_capture(capture, cache_dir=cache_dir, views=views, pixel_samples=pixel_samples)
    centres = None if obs.samples == 1 else observations_from_capture(capture, cache_dir=cache_dir, views=views)
    _warn_unused_frames(capture, obs, centres)
    lit = bool(np.max(np.asarray(obs.light_radiance), initial=0.0) > 0.0)
    env = None
    if model.ibl is not None or not lit:  # (read once: the tables and the check below share it)
        env = capture_environment(capture)
    if not lit and environment_is_dark(capture, env):
        # (no environment at all was refused with the observations)
        raise CaptureError(f"{capture.json_path}: no light reaches the mesh: the environment "
                           f"{capture.environment.file} is black, and every light is off or points away")
    centre_tables = visibility = bounce = occlusion = None
    parts = [obs] if centres is None else [centres, obs]
    rows = np.cumsum([0] + [o.num_rows for o in parts])
    row_normals = lambda: np.concatenate([np.asarray(o.normal) for o in parts])  # noqa: E731
    row_views = lambda: np.concatenate([np.asarray(o.view) for o in parts])  # noqa: E731
    if model.ibl is not None:
        visibility, cells, bounce, occlusion = _environment_visibility(capture, env, parts, options, model,
                                                                       cache_dir)
    t_ibl = time.perf_counter()
    both = direct = None
    if model.ibl == "per_pixel":
        report = options.progress
        direct, bounced = pixel_ibl_parts(env, row_normals(), row_views(), model, options.pixel_ibl_settings,
                                          cache_dir=cache_dir, progress=None if report is None else (
                                              lambda done, total: report(dict(stage="ibl", done=done, total=total))),
                                          visibility=visibility, bounce=bounce)
        both = direct if bounced is None else with_bounce(direct, bounced)
        if bounced is None or options.occlusion_settings.bounce != "auto":
            direct = None  # (kept only for the fit without the bounce)
        tables = dataclasses.replace(both, table=both.table[rows[-2]:])
    elif visibility is None and model.ibl is not None and options.background_compile:
        # built in a thread while the fit compiles its programs (`PendingTables`)
        tables = PendingTables.start(lambda: _ibl_for_capture(capture, model, env))
    else:
        tables = _ibl_for_capture(capture, model, env)
        if visibility is not None:  # the split sum's occlusion factors, one row per observation row
            both = OccludedTables(tables, to_device(split_sum_factors(visibility, cells, row_normals(), row_views())))
            tables = dataclasses.replace(both, table=both.table[rows[-2]:])
    if centres is not None and both is not None:
        centre_tables = dataclasses.replace(both, table=both.table[: rows[1]])
    t_ibl = time.perf_counter() - t_ibl
    setup = time.perf_counter() - t0
    result = fit_observations(obs, options, model=model, ibl=tables, setup_time=setup,
                              centres=centres, centre_ibl=centre_tables, select_footprint=select)
    _check_finite(result, capture)
    if direct is not None:
        # the same fit with the blocked directions dark (integrals of the same samples); the bounce
        # is kept where it explains the images clearly better, the other's time counts as "bounce_probe"
        dark = fit_observations(obs, options, model=model, ibl=dataclasses.replace(direct, table=direct.table[rows[-2]:]),
                                centres=centres, select_footprint=select, setup_time=setup,
                                centre_ibl=None if centres is None else dataclasses.replace(
                                    direct, table=direct.table[: rows[1]]))
        _check_finite(dark, capture)
        sigma = dict(bounce=fit_sigma(result.report), dark=fit_sigma(dark.report))
        kept = bounce_explains_better(dark.report, result.report)
        probe = dark if kept else result
        probe.report["times"]["setup"] = 0.0  # (the two fits share the setup: the kept one counts it)
        probe.report["wall_time"] -= setup
        result = _spent_before(result if kept else dark, probe, "bounce_probe")
        occlusion["bounce"].update(used=kept, residual_sigma=sigma)
    if isinstance(tables, PendingTables):
        t_ibl = tables.seconds  # (in its thread, beside the fit)
    if model.ibl is not None:
        result.report["ibl"] = dict(mode=model.ibl, seconds=t_ibl, **(
            dataclasses.asdict(options.pixel_ibl_settings) if model.ibl == "per_pixel" else {}))
        result.report["occlusion"] = occlusion
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
