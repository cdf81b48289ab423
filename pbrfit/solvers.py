"""The fit's objective and its structured Levenberg-Marquardt solver.

Objective (images' own space, see `pbrfit.observations`), for texel values x (T, K), K = 5
channels (`pbrfit.parameters`), or 7 when tangent-space normals are fitted too:

    E(x) = 1/2 Σ_p ||ρ̃(w_p ⊙ (encode(shade(m_p(x))) - target_p))||² + smooth/2 Σ_(a,b) ||x_a - x_b||²

where m_p(x) = Σ_k w_pk x_(t_pk) is the bilinear sample of pixel p (four texels t_pk, weights
w_pk), w_p the pixel's residual weights (`Observations.residual_weight`: 1, or the inverse of a
noise level that depends on the value, `pbrfit.noise`) and ρ̃ the residual transform of the
robust loss (identity for "l2"). With S samples per
pixel (`pbrfit.observations`, pixel footprints) shade(m_p(x)) becomes the mean linear radiance
of the pixel's samples, 1/S Σ_s shade_s(m_ps(x)), each sample s with its own geometry and its
own four texels.

Structure. A pixel's residual (3 numbers) depends on its K sampled values only, so its Jacobian
is J_p = ∂r_p/∂m_p (3 × K), computed exactly by forward mode (K tangents, `jax.jacfwd`, vmapped
over pixels). The full Jacobian is J_p w_pk in the columns of texel t_pk: the Gauss-Newton matrix
JᵀJ = Σ_p Σ_kl w_pk w_pl [t_pk, t_pl] ⊗ J_pᵀJ_p is block-sparse (K × K blocks between texels that
share a pixel), its diagonal blocks D_t = Σ w_pk² J_pᵀJ_p and the gradient g_t = Σ w_pk J_pᵀ r_p
are segment sums, and a product JᵀJ v costs one gather, a K × K product per pixel and one
scatter-add. With S samples the Jacobian of pixel p is J_ps = ∂r_p/∂m_ps (3 × K) per sample;
the products go through the pixel's residual space (JᵀJ v = Σ_s J_psᵀ Σ_s' J_ps' m_ps'(v)), and
the diagonal blocks sum, per pixel, the Jacobians of all its taps that read the same texel
before squaring (`normal_blocks`), so they stay exact where samples share texels. The damped normal equations

    (JᵀJ + λ diag(D) + smooth L) δ = -g

are solved by conjugate gradients preconditioned with the inverted diagonal blocks (block
Jacobi), in the span of the *active* channels: free, observed, and not on a bound that the
gradient pushes against. The step is clipped into the box (`pbrfit.parameters`), accepted if it
lowers E, and λ follows Nielsen's rule (H. B. Nielsen, "Damping parameter in Marquardt's method",
IMM-REP-1999-05). This is a projected Levenberg-Marquardt method (as in e.g. C. Kanzow et al.,
"Levenberg-Marquardt methods with strong local convergence properties for solving nonlinear
equations with convex constraints", 2004).

Why not an optimistix solver: optimistix's LM and Gauss-Newton take a lineax solver for the
step, but they do not support bounds (the active set and the projection live between the linear
solve and the acceptance test), and lineax's CG has no preconditioner hook for the block
diagonal we assemble from the same per-pixel Jacobians. So this loop is a jitted
`lax.while_loop` in plain JAX: no host round-trips, every array has a fixed shape, and pixels
and texels can be sharded. The generic optimistix solvers run the same objective through
`pbrfit.optx_solvers`.

Precision: every contraction here passes ``precision=HIGHEST``; JAX's default lets a GPU
multiply float32 in TF32 (10-bit mantissa), too coarse for the normal equations.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int

from .color import encode
from .model import Model
from .observations import Observations
from .material import apply_normal_map
from .parameters import lower, normal_from_slopes, upper
from .render import shade

__all__ = ["Problem", "LOSSES", "shading_normal", "pixel_residuals", "residuals", "linearize", "objective", "structured_lm",
           "normal_blocks", "neighbour_blocks", "NEIGHBOUR_OFFSETS", "gauss_newton_factors", "LMStats"]

#: Robust losses, as residual transforms r -> r sqrt(ρ(r²)/r²) (so the objective stays a sum of squares).
LOSSES = ("l2", "huber", "cauchy")
#: Relative floor on the damping diagonal, times the mean diagonal of the free channels: keeps the
#: damped blocks invertible for channels the images barely constrain (roughness without highlights).
DAMPING_FLOOR = 1e-6
#: Initial Levenberg-Marquardt damping (relative to the diagonal, Marquardt scaling).
LAMBDA_INIT = 1e-3
#: Damping above this means the model cannot be decreased further from here: stop.
LAMBDA_MAX = 1e10
#: Relative residual at which a step's conjugate gradients stop, ||r|| <= CG_RTOL ||g|| (an inexact
#: Levenberg-Marquardt step; `fit --cg-rtol` trades it for speed, measured in the README).
CG_RTOL = 1e-3
#: Below this ratio s = r²/c² the robust weights use their series (ρ(s)/s -> 1) to stay finite.
_ROBUST_SERIES = 1e-6


class Problem(eqx.Module):
    """One fitting problem: observations, the texels each pixel reads, which channels move.

    Attributes:
        obs: the usable pixels (`pbrfit.observations.Observations`).
        index, weight: (P, 4) texels read by each pixel and their bilinear weights.
        free: (T, K) 1 where a channel of a texel is fitted (free and observed), else 0.
        pairs: (E, 2) neighbouring texels for the smoothness prior; pair_weight (E,) 0 or 1.
        smooth: weight of the smoothness prior (0 = off).
        loss_scale: the robust loss's scale c, in image units.
        ibl: the environment's split-sum tables (``model.ibl == "split_sum"``), the pixels'
            `pbrfit.pixel_ibl.PixelIBL` (``"per_pixel"``, one row per pixel), or None.
        model, loss: static configuration.
    """

    obs: Observations
    index: Int[Array, "P 4"]
    weight: Float[Array, "P 4"]
    free: Float[Array, "T K"]
    pairs: Int[Array, "E 2"]
    pair_weight: Float[Array, " E"]
    smooth: Float[Array, ""]
    loss_scale: Float[Array, ""]
    ibl: object = None
    model: Model = eqx.field(static=True, default=Model())
    loss: str = eqx.field(static=True, default="l2")

    @property
    def num_texels(self) -> int:
        return int(self.free.shape[0])

    @property
    def samples(self) -> int:
        """Rows (samples) per pixel."""
        return self.obs.samples

    @property
    def num_pixels(self) -> int:
        return int(self.index.shape[0]) // self.obs.samples


def robust_residual(r, loss: str, scale):
    """r sqrt(ρ(r²)/r²): the residual whose square is the robust loss ρ(r²) (elementwise)."""
    if loss == "l2":
        return r
    c2 = scale * scale
    q = r * r / c2
    big = q > _ROBUST_SERIES
    q_safe = jnp.where(big, q, 1.0)
    if loss == "huber":
        # ρ(s) = s for s <= c², else 2 c sqrt(s) - c²  ->  ρ/s = 2/sqrt(q) - 1/q for q > 1.
        ratio = jnp.where(q_safe > 1.0, 2.0 / jnp.sqrt(q_safe) - 1.0 / q_safe, 1.0)
        ratio = jnp.where(big, ratio, 1.0)
    elif loss == "cauchy":
        # ρ(s) = c² log(1 + s/c²)  ->  ρ/s = log1p(q)/q.
        ratio = jnp.where(big, jnp.log1p(q_safe) / q_safe, 1.0 - 0.5 * q)
    else:
        raise ValueError(f"unknown loss {loss!r}; expected one of {', '.join(LOSSES)}")
    return r * jnp.sqrt(ratio)


def shading_normal(m: Float[Array, "*P K"], normal: Float[Array, "*P 3"], tangent: Float[Array, "*P 4"]):
    """The normal a pixel shades with: the geometric one, tilted by the fitted tangent-space
    normal (slopes in channels 5, 6) when normals are fitted (K = 7)."""
    if m.shape[-1] <= 5:
        return normal
    return apply_normal_map(normal, tangent, normal_from_slopes(m[..., 5:7]))


def _sample_radiance(m, normal, tangent, view, light_l, light_radiance, *lobes, problem: Problem):
    """Linear radiance (3,) of one pixel sample from its sampled (K,) material values (``lobes``:
    its row of per-pixel IBL integrals, when the model uses them)."""
    ibl = dataclasses.replace(problem.ibl, table=lobes[0][None]) if lobes else problem.ibl
    return shade(
        shading_normal(m, normal, tangent)[None], view[None], light_l[None], light_radiance[None],
        m[None, 0:3], m[None, 3:4], m[None, 4:5], problem.model, ibl,
    )[0]


def _value_residual(rad, exposure, target, residual_weight, problem: Problem):
    """Residual (3,) of one pixel from its (mean) linear radiance (3,), weighted by the inverse of
    its noise level (`Observations.residual_weight`) before the robust loss."""
    obs = problem.obs
    value = encode(rad, exposure, obs.tonemap, obs.color_space)
    return robust_residual((value - target) * residual_weight, problem.loss, problem.loss_scale)


def _pixel_residual(m, exposure, target, residual_weight, *sample_args, problem: Problem):
    """Residual (3,) of a pixel shaded at one sample from its sampled (K,) material values."""
    return _value_residual(_sample_radiance(m, *sample_args, problem=problem), exposure, target, residual_weight,
                           problem)


def _sample_args(problem: Problem):
    """Per-row arguments of `_sample_radiance` after the material values."""
    obs = problem.obs
    args = (obs.normal, obs.tangent, obs.view, obs.light_l, obs.light_radiance)
    return args + ((problem.ibl.table,) if problem.model.ibl == "per_pixel" else ())


def _value_args(obs: Observations):
    """Per-pixel arguments of `_value_residual` after the radiance (each pixel's first sample row)."""
    return obs.pixel_rows(obs.exposure), obs.pixel_rows(obs.target), obs.pixel_rows(obs.residual_weight)


def _pixel_args(problem: Problem):
    """Per-row arguments of `_pixel_residual` after the material values."""
    obs = problem.obs
    return (obs.exposure, obs.target, obs.residual_weight) + _sample_args(problem)


def _by_pixel(a, problem: Problem):
    """(R, ...) rows -> (P, S, ...)."""
    return a.reshape((problem.num_pixels, problem.samples) + a.shape[1:])


def _value_and_jacfwd(f, x):
    """(f(x), ∂f/∂x) by forward mode, f evaluated once."""
    jac, value = jax.jacfwd(lambda v: (f(v), f(v)), has_aux=True)(x)
    return value, jac


def sample_texels(x: Float[Array, "T K"], problem: Problem) -> Float[Array, "P K"]:
    """Bilinear samples m_p = Σ_k w_pk x_(t_pk)."""
    return jnp.einsum("pk,pkc->pc", problem.weight, x[problem.index], precision=lax.Precision.HIGHEST)


def pixel_residuals(x: Float[Array, "T K"], problem: Problem) -> Float[Array, "P 3"]:
    """Every pixel's (transformed) residual at texel values x."""
    m = sample_texels(x, problem)
    if problem.samples == 1:
        f = jax.vmap(lambda mm, *a: _pixel_residual(mm, *a, problem=problem))
        return f(m, *_pixel_args(problem))
    rad = jax.vmap(lambda mm, *a: _sample_radiance(mm, *a, problem=problem))(m, *_sample_args(problem))
    obs = problem.obs
    mean = jnp.mean(_by_pixel(rad, problem), axis=1)
    f = jax.vmap(lambda rr, e, t, w: _value_residual(rr, e, t, w, problem))
    return f(mean, *_value_args(obs))


def _smooth_residuals(x, problem: Problem):
    a, b = problem.pairs[:, 0], problem.pairs[:, 1]
    chan = jnp.max(problem.free, axis=0)  # channels the fit frees
    return jnp.sqrt(problem.smooth) * problem.pair_weight[:, None] * chan * (x[a] - x[b])


def residuals(x: Float[Array, "T K"], problem: Problem):
    """All residuals as a pytree (pixels, smoothness prior): E = 1/2 Σ leaves²."""
    return pixel_residuals(x, problem), _smooth_residuals(x, problem)


def objective(x: Float[Array, "T K"], problem: Problem) -> Float[Array, ""]:
    """E(x) = 1/2 Σ residuals²."""
    r, s = residuals(x, problem)
    return 0.5 * (jnp.sum(r * r) + jnp.sum(s * s))


def linearize(x: Float[Array, "T K"], problem: Problem):
    """Residuals (P, 3), per-pixel Jacobians J_p = ∂r_p/∂m_p (P, 3, K) (per sample row,
    (R, 3, K), with several samples per pixel) and E(x)."""
    m = sample_texels(x, problem)

    if problem.samples == 1:
        one = lambda mm, *a: _value_and_jacfwd(lambda v: _pixel_residual(v, *a, problem=problem), mm)  # noqa: E731
        r, jac = jax.vmap(one)(m, *_pixel_args(problem))
    else:
        r, jac = _linearize_samples(m, problem)
    s = _smooth_residuals(x, problem)
    loss = 0.5 * (jnp.sum(r * r) + jnp.sum(s * s))
    return r, jac, loss


def _linearize_samples(m, problem: Problem):
    """Pixel residuals (P, 3) and per-sample Jacobians J_ps = ∂r_p/∂m_ps (R, 3, K): the chain
    of each sample's radiance Jacobian (forward mode, K tangents) and the Jacobian of the
    pixel's encoding and loss at the mean radiance (3 tangents), divided by S."""

    sample = lambda mm, *a: _value_and_jacfwd(lambda v: _sample_radiance(v, *a, problem=problem), mm)  # noqa: E731
    rad, jrad = jax.vmap(sample)(m, *_sample_args(problem))
    mean = jnp.mean(_by_pixel(rad, problem), axis=1)
    pixel = lambda rr, e, t, w: _value_and_jacfwd(lambda v: _value_residual(v, e, t, w, problem), rr)  # noqa: E731
    r, jenc = jax.vmap(pixel)(mean, *_value_args(problem.obs))
    jac = jnp.einsum("pab,psbk->psak", jenc, _by_pixel(jrad, problem), precision=lax.Precision.HIGHEST)
    return r, jac.reshape(jrad.shape) / problem.samples


def _to_rows(a, problem: Problem):
    """(P, ...) per pixel -> (R, ...) per sample row (repeated)."""
    return a if problem.samples == 1 else jnp.repeat(a, problem.samples, axis=0)


def _scatter(values, problem: Problem):
    """Σ over (p, k) with t_pk = t of values[p, k] -> (T, ...)."""
    flat = values.reshape((-1,) + values.shape[2:])
    return jax.ops.segment_sum(flat, problem.index.reshape(-1), num_segments=problem.num_texels)


def _laplacian(v, problem: Problem):
    a, b = problem.pairs[:, 0], problem.pairs[:, 1]
    chan = jnp.max(problem.free, axis=0)
    d = problem.pair_weight[:, None] * chan * (v[a] - v[b])
    t = problem.num_texels
    return jax.ops.segment_sum(d, a, num_segments=t) - jax.ops.segment_sum(d, b, num_segments=t)


def _degree(problem: Problem):
    t = problem.num_texels
    w = problem.pair_weight
    return jax.ops.segment_sum(w, problem.pairs[:, 0], num_segments=t) + jax.ops.segment_sum(
        w, problem.pairs[:, 1], num_segments=t)


def normal_blocks(jac: Float[Array, "R 3 K"], problem: Problem) -> Float[Array, "T K K"]:
    """Diagonal K × K blocks of JᵀJ (pixels only, no prior): D_t = Σ w_pk² J_pᵀ J_p.

    With S samples per pixel, a pixel's 4 S taps (sample s, bilinear tap k) have Jacobians
    A_j = w_j J_ps; taps that read the same texel add up before squaring:
    D_t = Σ_p B_ptᵀ B_pt with B_pt = Σ_(j: t_j = t) A_j, one segment sum over the pixel's distinct
    texels (memory linear in the taps)."""
    if problem.samples == 1:
        gp = jnp.einsum("pci,pcj->pij", jac, jac, precision=lax.Precision.HIGHEST)
        w2 = problem.weight * problem.weight
        return _scatter(w2[:, :, None, None] * gp[:, None], problem)
    p, taps = problem.num_pixels, 4 * problem.samples
    index = problem.index.reshape(p, taps)
    a = (problem.weight[:, :, None, None] * jac[:, None]).reshape((p * taps,) + jac.shape[1:])
    # number each pixel's distinct texels (sort its taps; a new run starts a new texel), so that
    # B, the sum of the A_j of each (pixel, texel), is one segment sum of size O(taps) per pixel
    order = jnp.argsort(index, axis=1)
    ranked = jnp.take_along_axis(index, order, axis=1)
    start = jnp.concatenate([jnp.ones((p, 1), bool), ranked[:, 1:] != ranked[:, :-1]], axis=1)
    run = jnp.cumsum(start, axis=1) - 1 + taps * jnp.arange(p)[:, None]
    segment = jnp.zeros_like(index).at[jnp.arange(p)[:, None], order].set(run).reshape(-1)
    b = jax.ops.segment_sum(a, segment, num_segments=p * taps)
    texel = jnp.zeros(p * taps, index.dtype).at[segment].set(index.reshape(-1))  # unused segments: B = 0
    bb = jnp.einsum("sci,scq->siq", b, b, precision=lax.Precision.HIGHEST)
    return jax.ops.segment_sum(bb, texel, num_segments=problem.num_texels)


#: The grid offsets (di, dj) of the coupling blocks `neighbour_blocks` keeps: half of the eight
#: neighbours, the block towards the other half being a transpose (A_(t, t-o) = A_(t-o, t)ᵀ).
NEIGHBOUR_OFFSETS = ((0, 1), (1, -1), (1, 0), (1, 1))


def _grid_step(d, n: int):
    """A difference of grid coordinates, wrapped on a ring of n, as -1, 0 or 1; 2 where the two
    are further apart, or where n = 2 makes +1 and -1 the same texel."""
    d = jnp.mod(d, n)
    if n == 1:
        return jnp.zeros_like(d)
    near = jnp.where(d == 0, 0, jnp.where(d == 1, 1, jnp.where(d == n - 1, -1, 2)))
    return jnp.where((n == 2) & (d == 1), 2, near)


def neighbour_blocks(jac: Float[Array, "R 3 K"], problem: Problem, shape: tuple[int, int]) -> Float[Array, "T 4 K K"]:
    """Off-diagonal K × K blocks of JᵀJ (pixels only, no prior) between neighbouring texels of
    the (H, W) map, flat index t = i W + j:

        C_(t,o) = A_(t, t+o) = Σ_p Σ_(a: t_a = t) Σ_(b: t_b = t+o) A_aᵀ A_b,

    for the offsets o of `NEIGHBOUR_OFFSETS` (grid steps wrapped around the map, as the "repeat"
    sampler reads it), over every ordered pair (a, b) of pixel p's 4 S taps, A_a = w_a J_(p,s_a).
    With `normal_blocks`' diagonal blocks these are every block of JᵀJ whose texels lie within
    one step of each other; pairs of a pixel's taps further apart (a pixel footprint wider than a
    texel) are left out. On a map one texel high (or wide) a step across it leads back to the
    texel's own row, and those offsets' blocks stay zero; on one two texels high, +1 and -1 are
    the same texel, and the pairs across are left out (`pbrfit.uncertainty.window_radii` gives
    such an axis no window). One scan step per unordered pair of taps (6 at pixel centres, 120 with 2 × 2 samples)
    takes each pixel's two Jacobians from ``jac`` and scatter-adds their product: memory is that
    of the result. (With pixels split over devices, each step sums the result over them.)"""
    h, w = shape
    p, samples = problem.num_pixels, problem.samples
    taps = 4 * samples
    k = jac.shape[-1]
    t = problem.num_texels
    index = problem.index.reshape(p, taps)
    weight = problem.weight.reshape(p, taps)
    jac = _by_pixel(jac, problem)  # (P, S, 3, K)
    slots = len(NEIGHBOUR_OFFSETS)
    table = np.full((3, 3), -1, np.int32)  # (di + 1, dj + 1) -> offset number, -1 = not kept
    for n, (di, dj) in enumerate(NEIGHBOUR_OFFSETS):
        table[di + 1, dj + 1] = n
    table = jnp.asarray(table)

    def code(ta, tb):
        di, dj = _grid_step(tb // w - ta // w, h), _grid_step(tb % w - ta % w, w)
        far = (di == 2) | (dj == 2)
        return jnp.where(far, -1, table[jnp.clip(di, -1, 1) + 1, jnp.clip(dj, -1, 1) + 1])

    pairs = jnp.asarray(np.array([(i, j) for i in range(taps) for j in range(i + 1, taps)], np.int32))

    def step(acc, pair):
        a, b = pair[0], pair[1]
        ta, tb = index[:, a], index[:, b]
        ja = weight[:, a, None, None] * jac[:, a // 4]
        jb = weight[:, b, None, None] * jac[:, b // 4]
        g = jnp.einsum("pci,pcj->pij", ja, jb, precision=lax.Precision.HIGHEST)
        forward, backward = code(ta, tb), code(tb, ta)
        # a pair is stored once: from a towards b where b - a is a kept offset, else from b as Gᵀ;
        # pairs of one texel (the diagonal blocks) and pairs further apart go out of range
        use_forward = forward >= 0
        slot = jnp.where(use_forward, ta * slots + forward, jnp.where(backward >= 0, tb * slots + backward, t * slots))
        g = jnp.where(use_forward[:, None, None], g, jnp.swapaxes(g, 1, 2))
        return acc.at[slot].add(g, mode="drop"), None

    acc = jnp.zeros((t * slots, k, k), jac.dtype)
    acc, _ = lax.scan(step, acc, pairs)
    return acc.reshape(t, slots, k, k)


def gradient(r, jac, x, problem: Problem) -> Float[Array, "T K"]:
    """g = Jᵀ r (+ smooth L x)."""
    jr = jnp.einsum("pci,pc->pi", jac, _to_rows(r, problem), precision=lax.Precision.HIGHEST)
    return _scatter(problem.weight[:, :, None] * jr[:, None, :], problem) + problem.smooth * _laplacian(x, problem)


def gauss_newton_factors(jac: Float[Array, "R 3 K"], problem: Problem):
    """What `gn_product` needs of the Jacobians: the per-pixel J_pᵀJ_p (P, K, K) with one
    sample per pixel, else the per-sample Jacobians themselves."""
    if problem.samples == 1:
        return jnp.einsum("pci,pcj->pij", jac, jac, precision=lax.Precision.HIGHEST)
    return jac


def gn_product(gp, v, problem: Problem):
    """(JᵀJ + smooth L) v from `gauss_newton_factors` (matrix-free)."""
    mv = sample_texels(v, problem)
    if problem.samples == 1:
        y = jnp.einsum("pij,pj->pi", gp, mv, precision=lax.Precision.HIGHEST)
    else:  # J v in the pixels' residual space, then back through each sample's Jacobian
        jac = _by_pixel(gp, problem)
        jv = jnp.einsum("psci,psi->pc", jac, _by_pixel(mv, problem), precision=lax.Precision.HIGHEST)
        y = jnp.einsum("psci,pc->psi", jac, jv, precision=lax.Precision.HIGHEST).reshape(mv.shape)
    return _scatter(problem.weight[:, :, None] * y[:, None, :], problem) + problem.smooth * _laplacian(v, problem)


def _vdot(a, b):
    return jnp.sum(a * b)


def pcg(matvec: Callable, b, precond: Callable, rtol, max_steps: int):
    """Preconditioned conjugate gradients from 0; returns (solution, iterations)."""
    x = jnp.zeros_like(b)
    z = precond(b)
    bnorm = jnp.sqrt(_vdot(b, b))
    init = (x, b, z, z, _vdot(b, z), 0)

    def cond(c):
        _, r, _, _, _, k = c
        return (k < max_steps) & (jnp.sqrt(_vdot(r, r)) > rtol * bnorm)

    def body(c):
        x, r, z, p, rz, k = c
        ap = matvec(p)
        pap = _vdot(p, ap)
        alpha = jnp.where(pap > 0, rz / jnp.where(pap > 0, pap, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * ap
        z = precond(r)
        rz_new = _vdot(r, z)
        beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
        return x, r, z, z + beta * p, rz_new, k + 1

    x, *_, k = lax.while_loop(cond, body, init)
    return x, k


class LMStats(eqx.Module):
    steps: Array
    accepted: Array
    cg_iterations: Array
    loss: Array
    damping: Array


def _active(x, g, free):
    lo = jnp.asarray(lower(x.shape[-1]), x.dtype)
    hi = jnp.asarray(upper(x.shape[-1]), x.dtype)
    blocked = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
    return free * (~blocked).astype(x.dtype)


@eqx.filter_jit
def structured_lm(
    x0: Float[Array, "T K"],
    problem: Problem,
    max_steps: int = 50,
    rtol: float = 1e-6,
    atol: float = 1e-5,
    cg_rtol: float = CG_RTOL,
    cg_max_steps: int = 100,
    progress: Optional[Callable] = None,
):
    """Projected Levenberg-Marquardt on the structured objective (module docstring).

    Stops after `max_steps` steps, or at an accepted step that lowers E by less than
    ``rtol · E`` or moves no value by more than `atol`. Returns (x, LMStats, residuals (P, 3),
    per-row Jacobians (R, 3, K); R = P with one sample per pixel) at the returned x.
    """
    k = x0.shape[-1]
    lo, hi = jnp.asarray(lower(k)), jnp.asarray(upper(k))
    x0 = jnp.clip(x0, lo, hi)
    p = problem.num_pixels
    eye = jnp.eye(k, dtype=x0.dtype)
    degree = _degree(problem)
    # Step 0 only linearises at x0 (no step is taken: every channel inactive), so the
    # linearisation is traced once, inside the loop.
    r0 = jnp.zeros((p, 3), x0.dtype)
    j0 = jnp.zeros((problem.index.shape[0], 3, k), x0.dtype)
    loss0 = jnp.asarray(jnp.inf, x0.dtype)

    def cond(c):
        return (c["k"] <= max_steps) & ~c["done"]

    def body(c):
        x, r, jac, loss, lam, nu = c["x"], c["r"], c["jac"], c["loss"], c["lam"], c["nu"]
        gp = gauss_newton_factors(jac, problem)
        g = gradient(r, jac, x, problem)
        blocks = normal_blocks(jac, problem) + problem.smooth * degree[:, None, None] * eye
        a = _active(x, g, problem.free) * (c["k"] > 0)
        diag = jnp.diagonal(blocks, axis1=1, axis2=2)
        mean_diag = jnp.sum(diag * problem.free) / jnp.maximum(jnp.sum(problem.free), 1.0)
        damp = diag + DAMPING_FLOOR * mean_diag
        outer = a[:, :, None] * a[:, None, :]
        m_blocks = outer * (blocks + lam * damp[:, :, None] * eye) + (1.0 - a)[:, :, None] * eye
        m_inv = jnp.linalg.inv(m_blocks)

        def matvec(v):
            av = a * v
            return a * (gn_product(gp, av, problem) + lam * damp * av) + (1.0 - a) * v

        def precond(v):
            return jnp.einsum("tij,tj->ti", m_inv, v, precision=lax.Precision.HIGHEST)

        delta, iters = pcg(matvec, -a * g, precond, cg_rtol, cg_max_steps)
        x_new = jnp.clip(x + a * delta, lo, hi)
        step = x_new - x
        predicted = -(_vdot(g, step) + 0.5 * _vdot(step, gn_product(gp, step, problem)))
        r_new, jac_new, loss_new = linearize(x_new, problem)
        actual = jnp.where(c["k"] > 0, loss - loss_new, 0.0)
        # step 0 only linearises at x0: kept even where the loss is not finite (an overflow), so
        # that the returned residuals and loss are x0's and the caller sees it, not zeros and inf
        accept = (c["k"] == 0) | (jnp.isfinite(loss_new) & (loss_new < loss))
        rho = actual / jnp.maximum(predicted, jnp.finfo(x.dtype).tiny)
        lam_new = jnp.where(accept, lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), lam * nu)
        nu_new = jnp.where(accept, 2.0, 2.0 * nu)
        small = (actual <= rtol * loss) | (jnp.max(jnp.abs(step)) <= atol)
        first = c["k"] == 0
        done = ~first & ((accept & small) | (lam_new > LAMBDA_MAX) | (jnp.max(jnp.abs(step)) == 0))
        lam_new = jnp.where(first, lam, lam_new)
        nu_new = jnp.where(first, nu, nu_new)
        if progress is not None:
            jax.debug.callback(progress, c["k"], jnp.where(accept, loss_new, loss))
        pick = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        return dict(
            x=pick(x_new, x), r=pick(r_new, r), jac=pick(jac_new, jac), loss=pick(loss_new, loss),
            lam=lam_new, nu=nu_new, k=c["k"] + 1, done=done,
            accepted=c["accepted"] + (accept & ~first).astype(jnp.int32),
            cg=c["cg"] + iters,
        )

    init = dict(x=x0, r=r0, jac=j0, loss=loss0, lam=jnp.asarray(LAMBDA_INIT, x0.dtype),
                nu=jnp.asarray(2.0, x0.dtype), k=jnp.asarray(0), done=jnp.asarray(False),
                accepted=jnp.asarray(0), cg=jnp.asarray(0))
    out = lax.while_loop(cond, body, init)
    stats = LMStats(jnp.maximum(out["k"] - 1, 0), out["accepted"], out["cg"], out["loss"], out["lam"])
    return out["x"], stats, out["r"], out["jac"]
