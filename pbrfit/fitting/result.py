"""What a fit returns: `FitResult` (maps, standard errors, coverage, renders, report), built from
the solution by `finish`, and `map_rmse` against ground truth maps."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Optional

import jax
import numpy as np

from .stages.footprint import samples_side
from ..physics.material import Material
from .observations import coverage_counts, layout_for
from .parameters import CHANNELS, NORMAL_CHANNELS, lower, normal_from_slopes, upper
from .runner import announce, jitted_neighbour_blocks, jitted_normal_blocks, thread_time
from .solvers.names import solver_name
from .stages.selection import profile_hessian, uniform_direction
from .objective import linearize, objective, pixel_residuals
from ..physics.textures import resample_map
from ..transfer import to_device
from .uncertainty import (WINDOW_RADIUS, WindowCache, residual_variance, sandwich_ratios, window_radii,
                          window_standard_errors)

__all__ = ["FitResult", "closed_times", "finish", "map_rmse", "texel_standard_errors", "truth_at"]


@dataclasses.dataclass
class FitResult:
    """What `fit` returns.

    Attributes:
        material: the fitted maps (`pbrfit.physics.material.Material`; 1 × 1 for a uniform fit), with a
            tangent-space normal map when normals are fitted.
        uncertainty: (H, W, K) one-sigma errors (base R, G, B, metallic, roughness, and the
            normal's slopes s_x, s_y when normals are fitted), each texel's with the texels of
            its window free (``uncertainty_radius``); 0 for fixed channels, +inf for texels no
            view sees.
        coverage: (H, W) pixel observations per texel (0 = never seen; such texels keep `PRIOR`).
        report: model, solver, steps (also as "iterations", the capture spec's word), times
            (`closed_times`), final loss, per-view PSNR, devices, the levels run and the
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


def closed_times(times: dict, wall: float) -> dict:
    """A fit's time split, closed: ``times`` (setup: reading the capture, casting rays and building
    the environment's tables (the report's "ibl" entry gives their part); compile:
    waiting for compiles; solve: solver steps; init, search: the grid start and the coordinate
    search; repair, uniform_check: those stages' own work; post: the outputs' arrays;
    footprint_probe: the pixel-centre fit whose residuals showed a box footprint, before the fit
    of both; ibl_probe: the fit under the light model not kept; bounce_probe: the fit with or
    without the bounce not kept, `pbrfit.fitting.api.fit`) with
    "other", the rest of ``wall`` (host-side work between stages: each level's problem), so that
    the entries sum to the wall time. "compile_background", compiles overlapped with the fit's
    own work in another thread, is apart from the sum."""
    times = {k: float(v) for k, v in times.items() if k != "other"}
    return dict(times, other=max(float(wall) - thread_time(times), 0.0))


def texel_standard_errors(problem, x, jac, data_energy: float, final, texel_channels, seen, num_pixels: int,
                          num_uniform: int = 0, uncertainty_radius: int = WINDOW_RADIUS,
                          cache: Optional[WindowCache] = None):
    """(T, K) standard errors of the texels' channels at x, as uncertainty.exr gives them, and σ̂².

    σ̂² is the residual variance of the pixels' ``data_energy`` (½ Σ r²) over 3 × `num_pixels`
    residuals and the seen texels' `texel_channels` (plus `num_uniform` common values); each
    texel's σ comes from its window of ``uncertainty_radius``
    (`pbrfit.fitting.uncertainty.window_standard_errors`, which keeps its windows in ``cache``
    for a later call), with the channels that sit on a bound held for the others' errors; 0 for
    channels not fitted, +inf for texels no view sees."""
    blocks = np.asarray(jitted_normal_blocks(jac, problem))
    n_par = _parameter_count(seen, texel_channels, num_uniform)
    sigma2 = residual_variance(float(data_energy), 3 * int(num_pixels), n_par)
    radius = max(window_radii(tuple(final), uncertainty_radius))
    couplings = np.asarray(jitted_neighbour_blocks(jac, problem, tuple(final))) if radius > 0 else None
    sigma = window_standard_errors(blocks, couplings, tuple(final), np.asarray(texel_channels) > 0, seen, sigma2,
                                   radius, _on_bounds(x, len(texel_channels)), cache)
    return sigma, sigma2


def _parameter_count(seen, texel_channels, num_uniform: int) -> int:
    """The fit's free parameters: the seen texels' fitted channels and the common values."""
    return int(np.sum(seen)) * int(np.sum(texel_channels)) + int(num_uniform)


def _on_bounds(x, k: int) -> np.ndarray:
    """(T, K) the channels that sit on a bound of their range: the projected solver holds them."""
    xt = np.asarray(x, np.float32).reshape(-1, k)
    return (xt <= lower(k)) | (xt >= upper(k))


def misfit_ratios(problem, x, r, jac, sigma2: float, texel_channels, seen, num_pixels: int, num_uniform: int = 0):
    """(T, K) how much more variance each texel's pixels show than σ̂² accounts for, at least 1:
    the sandwich's ratio (`pbrfit.fitting.uncertainty.sandwich_ratios`) of its block, with the
    channels on a bound held as `texel_standard_errors` holds them. The pooled σ̂² is the better
    estimate of the noise (every residual of the fit against a texel's few dozen), so a ratio
    under 1 is read as that estimate's scatter, and only the excess widens σ: the variance of a
    texel whose pixels the model does not fit as well as the rest (light it cannot represent, a
    wrong basin). The meat's rows, r_pᵀ J_p, go into the Jacobians' first residual channel
    (the others 0), placed as the Jacobians are, so that `normal_blocks`' program for the
    Jacobians serves them (jit compiles again for an argument committed to a device where the
    Jacobians are not, and the other way round, and keys a host array apart from a device one)."""
    jac_np = np.asarray(jac, np.float32)
    rows = np.repeat(np.asarray(r, np.float32), problem.samples, axis=0)[: jac_np.shape[0]]
    g = np.zeros_like(jac_np)
    g[:, 0, :] = np.einsum("rc,rck->rk", rows, jac_np)
    if isinstance(jac, jax.Array):
        g = jax.device_put(g, jac.sharding) if jac.committed else jax.device_put(g)
    meat = np.asarray(jitted_normal_blocks(g, problem))
    blocks = np.asarray(jitted_normal_blocks(jac, problem))
    n = 3 * int(num_pixels)
    dof_scale = n / max(n - _parameter_count(seen, texel_channels, num_uniform), 1)
    ratios = sandwich_ratios(blocks, meat, np.asarray(texel_channels) > 0, seen, sigma2, dof_scale,
                             _on_bounds(x, len(texel_channels)))
    return np.maximum(ratios, 1.0)


def finish(obs, state, x, model, options, history, times, t_start):
    """The result at the fit's x. The maps' standard errors come from each texel's window of
    ``uncertainty_radius`` (`pbrfit.fitting.uncertainty.window_standard_errors`; 0: its own block), with
    the channels that sit on a bound held for the others' errors, widened where the texel's own
    pixels show more variance than σ̂² (`misfit_ratios`).
    ``uniform`` {channel: value}: channels fitted as one common value
    (`pbrfit.fitting.stages.selection.run_uniform_check`); their standard errors, at every seen texel, are
    σ̂ sqrt(diag(P⁻¹)) for P their profile curvature matrix (`pbrfit.fitting.stages.selection.profile_hessian`).

    ``state``: the `pbrfit.fitting.stages.pipeline.StageState` the stages after the solve left
    (the final problem, map shape, channels, texels seen, linearisation at ``x`` or None, and
    the uniform channels); ``options``: the fit's `pbrfit.fitting.options.FitOptions`;
    ``times``: the clock so far; ``t_start``: when the pass began."""
    t_post = time.perf_counter()
    problem, final, channels, seen = state.problem, state.final, state.channels, state.seen
    linearization, uniform = state.linearization, dict(state.uniform or {})
    loss, smooth, wrap = options.loss, options.smooth, options.wrap
    uncertainty_radius = int(options.uncertainty_radius)
    solver = solver_name(options.solver)
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
    # σ̂² from the pixels' residuals: the prior's energy is no noise (with it, σ̂ grew with --smooth;
    # 0.060 at weight 1 under noise 0.05). The blocks, too, are the pixels' alone: σ says what the
    # images constrain, the prior not counted.
    data_energy = energy if float(problem.smooth) == 0 else 0.5 * np.sum(np.square(np.asarray(r, np.float64)))
    if state.errors is not None:  # the hold's, at this x
        sigma, sigma2 = state.errors
    else:
        announce(options.progress, state.where, "standard errors")
        sigma, sigma2 = texel_standard_errors(problem, x, jac, float(data_energy), final, texel_channels, seen,
                                              obs.num_pixels, len(uniform), uncertainty_radius)
    sigma = sigma * np.sqrt(misfit_ratios(problem, x, r, jac, sigma2, texel_channels, seen, obs.num_pixels,
                                          len(uniform))).astype(np.float32)
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
    coverage = coverage_counts(layout_for(obs, final, wrap), obs.samples)
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
        pixel_samples=samples_side(obs),
        observed_texels=int(np.sum(coverage > 0)),
        unseen_texels=int(np.sum(coverage == 0)),  # left at the prior (or held), σ +inf
        psnr=psnr,
        wall_time=float(times["setup"] + time.perf_counter() - t_start),
        devices=sorted(str(d) for d in problem.obs.target.sharding.device_set),
        uncertainty=dict(radius=int(uncertainty_radius), window=[2 * r + 1 for r in window_radii(tuple(final),
                                                                                               uncertainty_radius)]),
    )
    report["times"] = closed_times(times, report["wall_time"])
    if tuple(final) == (1, 1):  # a uniform material: the five numbers and their standard errors
        report["material"] = dict(base_color=[float(v) for v in x[0, 0, 0:3]], metallic=float(x[0, 0, 3]),
                                  roughness=float(x[0, 0, 4]))
        report["material_sigma"] = dict(base_color=[float(v) for v in sigma[0, 0, 0:3]],
                                        metallic=float(sigma[0, 0, 3]), roughness=float(sigma[0, 0, 4]))
    return FitResult(material, sigma, coverage, report, images, targets, masks)


def truth_at(truth: Material, shape: tuple[int, int]) -> Material:
    """The true base colour, metallic and roughness maps at a fitted resolution, as a held map is
    resampled (`pbrfit.physics.textures.resample_map`: block means for whole factors, else
    linear); the normal map as it is."""
    maps = {name: resample_map(getattr(truth, name), shape) for name in ("base_color", "metallic", "roughness")}
    return dataclasses.replace(truth, **maps)


def map_rmse(truth: Material, result, coverage: Optional[np.ndarray] = None) -> dict:
    """Per-map RMSE of a fitted material (or `FitResult`) against the truth, over observed texels.

    The truth is resampled to the fitted resolution when sizes differ, as a held map is
    (`pbrfit.physics.textures.resample_map`: block means for whole factors, else linear).
    """
    material = result.material if isinstance(result, FitResult) else result
    if coverage is None and isinstance(result, FitResult):
        coverage = result.coverage
    shape = material.resolution
    truth = truth_at(truth, shape)
    out = {}
    for name in ("base_color", "metallic", "roughness"):
        t = np.asarray(getattr(truth, name), np.float32)
        f = np.asarray(getattr(material, name), np.float32)
        seen = np.ones(shape, bool) if coverage is None else np.asarray(coverage) > 0
        err = (f - t)[seen]
        out[name] = float(np.sqrt(np.mean(err ** 2))) if err.size else float("nan")
    return out
