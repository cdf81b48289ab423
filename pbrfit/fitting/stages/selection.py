"""Model selection: one value instead of a map where the images do not support the map.

A channel fitted as a map of T texels has T parameters; held at one common value it has one.
Where the images cannot tell that channel's texels apart (a dielectric plane's metallic under
noise, the roughness of a surface no highlight reaches twice), the map fits the noise: its
texels scatter about the truth by their standard errors σ_t, and through the channels they are
correlated with (base colour with metallic) they drag the others along. One value fitted from
every pixel has no such scatter, but errs by the truth's own spread about its mean.

Akaike's information criterion (H. Akaike, "A new look at the statistical model
identification", IEEE Trans. Automatic Control 19(6), 1974) weighs the two: with Gaussian
residuals it is 2E/σ² + 2·(parameters), for the data term E = ½ Σ r². The common value is kept
when

    Δ = 2 (E_uniform − E_map) / σ̂²  ≤  2 (T − 1),

σ̂² the map fit's residual variance (`pbrfit.fitting.uncertainty.residual_variance`). For nested
least-squares models Δ's expectation is (T − 1) + Σ_t (m_t − m̄)² / σ_t² (its degrees of freedom
plus the non-centrality of the true map m about its mean), so the test keeps the common value
when the truth's spread about its mean is below the map's own noise: when the common value is
the smaller error too.

The common value is the profile-likelihood estimate: the other channels re-fitted at each
trial value c, projected Newton steps on c (clipped to the channel's bounds) with

    dE_uniform/dc ≈ eᵀ ∇E,   d²E_uniform/dc² ≈ eᵀ H e,   e = d − F (Fᵀ H F)⁻¹ Fᵀ H d,

d the direction that moves channel c of every seen texel together, H = JᵀJ the Gauss-Newton
matrix and F the channels still fitted: e moves the common value and re-fits the others to
first order (`profile_hessian`; eᵀ H e is the Schur complement dᵀHd − dᵀHF (FᵀHF)⁻¹ FᵀHd, one
conjugate-gradient solve over the whole map, since neighbouring texels share pixels; eᵀ ∇E is
the envelope theorem's dᵀ∇E where the others are at their optimum, and stays right where a
re-fit stopped short of it). The value's standard
error is sqrt(σ̂² / that curvature), or, with both channels uniform, from the inverse of their
2 × 2 profile matrix. Bounds of the other channels are ignored in it.

Before any re-fit, a Wald statistic W = Σ_t s_t (x_t − c₀)² / σ̂² of the map's own values about
their precision-weighted mean c₀ approximates Δ, with s_t = 1 / [(D_t)⁻¹]_cc the channel's
precision in texel t from its own Gauss-Newton block D_t (`pbrfit.fitting.normal_matrix.normal_blocks`, the
other channels of the texel re-fitted; 0 where `pbrfit.fitting.uncertainty` finds the channel
unconstrained). The blocks leave out what neighbouring texels share, so s_t overstates the
precision (on the tests' scene W was twice Δ; on the noisy peer planes 0.7 to 1.4 times it); a
map with W above `WALD_MARGIN` times the threshold is kept without re-fitting. That keeps every map of our textured scenes, and
also a map that a fit left in a wrong minimum, whose scatter is not noise. Texels with s_t = 0
count as no parameter in the threshold.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from ..parameters import lower, upper
from ..runner import fit_jit, jitted_normal_blocks, problem_energy
from ..solvers.names import DEFAULT_SOLVER, is_structured
from ..objective import Problem
from ..normal_matrix import gradient, spd_block_inverse
from ..solvers.structured import pcg
from ..stencil import gauss_newton_operator, gauss_newton_product
from ...transfer import to_device
from ..uncertainty import block_standard_errors, residual_variance

__all__ = ["SELECTABLE", "WALD_MARGIN", "NEWTON_STEPS", "aic_statistic", "prefers_uniform", "texel_precisions",
           "profile_hessian", "uniform_direction", "wald_statistic", "weighted_value", "newton_value", "REFIT_STEPS",
           "NEWTON_TOL", "uniform_channels", "uniform_check_skipped", "run_uniform_check"]

#: Channels the test may make uniform: (name, channel index). Base colour is always a map.
SELECTABLE = (("metallic", 3), ("roughness", 4))
#: A map whose Wald statistic is above this multiple of the test's threshold is kept unchallenged.
WALD_MARGIN = 4.0
#: Newton steps on the common value (each one re-fit of the other channels).
NEWTON_STEPS = 3
#: `profile_hessian`'s conjugate gradients: relative residual and iteration cap.
PROFILE_CG_RTOL = 1e-4
PROFILE_CG_STEPS = 200
#: ... its block-Jacobi preconditioner adds this fraction of each block's largest diagonal entry
#: to the block, which keeps the block invertible in float32 where a channel is barely
#: constrained (the ridge is in the preconditioner only: the solve is of the exact system) ...
PRECONDITIONER_RIDGE = 1e-5
#: ... plus this fraction of the mean diagonal, for a block whose entries are all 0 (a texel
#: whose other channels no pixel constrains).
PRECONDITIONER_FLOOR = 1e-12
#: The uniform check (``uniform_check=True``, `run_uniform_check`): steps of each re-fit of the
#: other channels at a trial common value (on noisy images they stop at this cap, leaving
#: E_uniform a little high, which leans the test towards the map; the re-fits also continue the
#: map fit's own descent, which leans it the other way where that had not converged), and the
#: Newton step on that value, in units of its standard error, below which the value is final (it
#: moves the test statistic by its square).
REFIT_STEPS = 10
NEWTON_TOL = 1.0


def texel_precisions(blocks: np.ndarray, channels: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(T, K) s_tc = 1 / [(D_t)⁻¹]_cc over the fitted channels: each channel's curvature in texel t
    with the texel's other fitted channels re-fitted (the Schur complement of its block); 0 for
    unseen texels, fixed channels and where the block leaves a channel unconstrained
    (`EIGEN_FLOOR`, as `pbrfit.fitting.uncertainty.block_standard_errors` finds it). One eigen-
    decomposition of the blocks serves every channel."""
    sigma = block_standard_errors(blocks, channels, seen, 1.0).astype(np.float64)
    ok = np.isfinite(sigma) & (sigma > 0)
    return np.where(ok, 1.0 / np.where(ok, sigma, 1.0) ** 2, 0.0)


@fit_jit
def profile_hessian(r: Float[Array, "P 3"], jac: Float[Array, "R 3 K"], x: Float[Array, "T K"], problem: Problem,
                    directions: Float[Array, "U T K"]):
    """((U, U), (U,)): the Gauss-Newton curvature and the slope of E along `directions` with the
    channels ``problem.free`` holds re-fitted to first order.

    Each direction d_u becomes e_u = d_u − F y_u, y_u = (Fᵀ H F)⁻¹ Fᵀ H d_u (H = JᵀJ of the pixels,
    F the free entries; block-Jacobi preconditioned conjugate gradients over the whole map, whose
    products go by stencil where the problem has one, `pbrfit.fitting.stencil`: on the peer scene
    the check's two calls took 84 ms through the pixels and 40 by stencil), and
    P_uv = e_uᵀ H e_v (= Dᵀ H D − Dᵀ H F (Fᵀ H F)⁻¹ Fᵀ H D, positive semi-definite as computed),
    g_u = e_uᵀ ∇E: the Newton step on the common values is −P⁻¹ g even where the re-fit of the
    others stopped short of their optimum."""
    free = problem.free
    k = free.shape[1]
    blocks, factors = gauss_newton_operator(jac, problem, problem.stencil)

    def product(v):
        return gauss_newton_product(factors, v, problem, problem.stencil)

    diag = jnp.diagonal(blocks, axis1=1, axis2=2)
    ridge = (PRECONDITIONER_RIDGE * jnp.max(diag * free, axis=1)
             + PRECONDITIONER_FLOOR * jnp.sum(diag * free) / jnp.maximum(jnp.sum(free), 1.0))
    eye = jnp.eye(k, dtype=blocks.dtype)
    m = free[:, :, None] * free[:, None, :] * (blocks + ridge[:, None, None] * eye) + (1.0 - free)[:, :, None] * eye
    m_inv = spd_block_inverse(m)

    def matvec(v):
        return free * product(free * v)

    def precond(v):
        return jnp.einsum("tij,tj->ti", m_inv, v, precision=lax.Precision.HIGHEST)

    e = jnp.stack([d - free * pcg(matvec, free * product(d), precond, PROFILE_CG_RTOL, PROFILE_CG_STEPS)[0]
                   for d in directions])
    he = jnp.stack([product(v) for v in e])
    p = jnp.einsum("utk,vtk->uv", e, he, precision=lax.Precision.HIGHEST)
    g = jnp.einsum("utk,tk->u", e, gradient(r, jac, x, problem), precision=lax.Precision.HIGHEST)
    return 0.5 * (p + p.T), g


def uniform_direction(seen: np.ndarray, c: int, k: int) -> np.ndarray:
    """(T, K) the direction that moves channel c of every seen texel by one."""
    d = np.zeros((len(seen), k), np.float32)
    d[np.asarray(seen, bool), c] = 1.0
    return d


def weighted_value(values: np.ndarray, precision: np.ndarray, lo: float, hi: float) -> float:
    """The precision-weighted mean of a channel's texel values, within [lo, hi] (the plain mean
    where no texel has any precision)."""
    values = np.asarray(values, np.float64)
    w = np.asarray(precision, np.float64)
    mean = float(np.sum(w * values) / np.sum(w)) if np.sum(w) > 0 else float(np.mean(values))
    return float(np.clip(mean, lo, hi))


def wald_statistic(values: np.ndarray, precision: np.ndarray, value: float, sigma2: float) -> float:
    """W = Σ_t s_t (x_t − c)² / σ̂²: the squared distance of the map from one value, in units of its
    standard errors (the test statistic's approximation from the map fit alone)."""
    d = np.asarray(values, np.float64) - value
    return float(np.sum(np.asarray(precision, np.float64) * d * d) / max(sigma2, np.finfo(np.float64).tiny))


def newton_value(value: float, gradient_sum: float, curvature: float, lo: float, hi: float) -> float:
    """One projected Newton step on the common value: clip(c − slope / curvature, lo, hi)."""
    if not curvature > 0:
        return value
    return float(np.clip(value - gradient_sum / curvature, lo, hi))


def aic_statistic(loss_uniform: float, loss_map: float, sigma2: float) -> float:
    """Δ = 2 (E_uniform − E_map) / σ̂², E = ½ Σ r² of each fit."""
    return 2.0 * (float(loss_uniform) - float(loss_map)) / max(sigma2, np.finfo(np.float64).tiny)


def prefers_uniform(statistic: float, texels: int) -> bool:
    """Akaike's choice: the common value where Δ ≤ 2 (T − 1) for a map of T free texels."""
    return statistic <= 2.0 * (texels - 1)


def uniform_channels(report: dict) -> list[str]:
    """Names of the channels a fit's uniform check made one common value (its report's
    "uniform_check" entries with ``uniform``)."""
    return [name for name, c in report.get("uniform_check", {}).items() if isinstance(c, dict) and c.get("uniform")]


def uniform_check_skipped(solver, loss, smooth, final, channels) -> Optional[str]:
    """Why the uniform check does not apply to a fit, or None where it does."""
    if tuple(final) == (1, 1):
        return "a uniform material"
    if not is_structured(solver):
        return f"needs the {DEFAULT_SOLVER} solver"
    if loss != "l2":
        return f"needs the l2 loss (the test reads the data term as a Gaussian likelihood), not {loss}"
    if smooth > 0:
        return "the smoothness prior already ties the texels together"
    if not any(channels[c] > 0 for _, c in SELECTABLE):
        return "neither metallic nor roughness is fitted"
    return None


def run_uniform_check(runner, problem: Problem, xs, linearization, channels, seen, num_pixels: int, where: dict):
    """Metallic, then roughness, as one common value where Akaike's criterion prefers it to a map:
    (x, linearisation, problem, report, uniform) of the model kept, with
    ``uniform`` {channel: value} of the channels made uniform."""
    channels = np.asarray(channels, np.float32).copy()
    k = len(channels)
    lo, hi = lower(k), upper(k)
    seen_t = np.asarray(seen[: problem.num_texels], bool)
    n_seen = int(np.sum(seen_t))
    r, jac = linearization
    e_map = problem_energy(r, xs, problem)  # no prior here: the check is skipped with one
    sigma2 = residual_variance(e_map, 3 * num_pixels, n_seen * int(np.sum(channels)))
    xs = np.asarray(xs, np.float32)
    report, uniform = {}, {}
    precision = None  # per-texel precisions of the model as it stands (recomputed when a channel goes)
    for name, c in SELECTABLE:
        if channels[c] == 0:
            continue
        if precision is None:
            precision = texel_precisions(np.asarray(jitted_normal_blocks(jac, problem)), channels > 0, seen_t)
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
        e_uniform = problem_energy(r_red, x_red, reduced)
        statistic = aic_statistic(e_uniform, e_map, sigma2)
        keep = prefers_uniform(statistic, n_texels)
        report[name] = dict(entry, uniform=keep, statistic=statistic, value=value, steps=steps, values=values,
                            converged=converged)
        if keep:
            xs, linearization, problem, e_map = np.asarray(x_red, np.float32), (r_red, jac_red), reduced, e_uniform
            jac, channels, precision = jac_red, reduced_channels, None
            uniform[c] = value
    return xs, linearization, problem, report, uniform
