"""The fit's objective, its residuals and their Jacobians.

Objective (images' own space, see `pbrfit.fitting.observations`), for texel values x (T, K), K = 5
channels (`pbrfit.fitting.parameters`), or 7 when tangent-space normals are fitted too:

    E(x) = 1/2 Σ_p ||ρ̃(w_p ⊙ (encode(shade(m_p(x))) - target_p))||² + smooth/2 Σ_(a,b) ||x_a - x_b||²

where m_p(x) = Σ_k w_pk x_(t_pk) is the bilinear sample of pixel p (four texels t_pk, weights
w_pk), w_p the pixel's residual weights (`Observations.residual_weight`: 1, or the inverse of a
noise level that depends on the value, `pbrfit.fitting.noise`) and ρ̃ the residual transform of the
robust loss (identity for "l2"). With S samples per
pixel (`pbrfit.fitting.observations`, pixel footprints) shade(m_p(x)) becomes the mean linear radiance
of the pixel's samples, 1/S Σ_s shade_s(m_ps(x)), each sample s with its own geometry and its
own four texels.

A pixel's residual (3 numbers) depends on its K sampled values only, so its Jacobian is
J_p = ∂r_p/∂m_p (3 × K), computed exactly by forward mode (K tangents, `jax.jacfwd`, vmapped over
pixels; `linearize`); with S samples per pixel, J_ps = ∂r_p/∂m_ps (3 × K) per sample.
`pbrfit.fitting.normal_matrix` assembles the Gauss-Newton matrix from them, `pbrfit.fitting.solvers.structured` solves.
`Problem` holds one fitting problem; the gathers and scatters between pixels and texels
(`to_rows`, `by_pixel`, `scatter_texels`) and the prior's `laplacian` and `prior_degree` serve
both.

Precision: every contraction here passes ``precision=HIGHEST``; JAX's default lets a GPU
multiply float32 in TF32 (10-bit mantissa), too coarse for the normal equations.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int

from .defaults import LOSSES
from ..physics.color import encode
from ..physics.model import Model
from .observations import CELL_CORNERS, Observations
from ..physics.material import apply_normal_map
from .parameters import lower, normal_from_slopes, upper
from ..render.shade import shade
from ..lighting.pixel_ibl import per_row
from ..transfer import to_device

__all__ = ["Problem", "LeftOut", "LOSSES", "robust_residual", "shading_normal", "sample_texels", "sample_material",
           "pixel_residuals", "residuals",
           "objective", "linearize", "by_pixel", "to_rows", "scatter_texels", "TexelGrid", "texel_grid", "offset_texels", "laplacian",
           "prior_degree", "smooth_residuals"]

#: Below this ratio s = r²/c² the robust weights use their series (ρ(s)/s -> 1) to stay finite.
_ROBUST_SERIES = 1e-6


class TexelGrid(eqx.Module):
    """The (H, W) map the first H W of a problem's T texels form (flat t = i W + j; the texels past
    H W are a coarser level's padding), with its cells' corner tables, both in
    `pbrfit.fitting.observations.CELL_CORNERS` order and wrapped around the map: ``corners`` (T, 4)
    the texels at the corners of the cell that starts at t, ``corner_of`` (T, 4) the cells whose
    corner a texel t is (corner a of cell t - o_a). A padding texel is its own everywhere.

    The shape is an array, so one compiled program serves every level of a fit; the tables are
    made on the host (`texel_grid`) rather than by modular arithmetic in each program, where every
    loop that passes values by cells held its own copy of it (on the peer scene 39 of the
    coordinate search's 160 kernels, and a fifth of its compile time)."""

    shape: Int[Array, "2"]
    corners: Int[Array, "T 4"]
    corner_of: Int[Array, "T 4"]


def offset_texels(shape: tuple[int, int], num_texels: int, steps) -> Int[np.ndarray, "T N"]:
    """(T, N) int32, for each of ``num_texels`` texels whose first H W form the (H, W) map, the
    texel each grid step (di, dj) of ``steps`` leads to, wrapped around the map; a texel past H W
    (a coarser level's padding) leads to itself. A host table (`texel_grid`,
    `pbrfit.fitting.stencil.with_stencil`)."""
    h, w = (int(n) for n in shape)
    t = np.arange(num_texels, dtype=np.int64)[:, None]
    di, dj = (np.asarray([s[n] for s in steps], np.int64) for n in (0, 1))
    return np.where(t < h * w, np.mod(t // w + di, h) * w + np.mod(t % w + dj, w), t).astype(np.int32)


def texel_grid(shape: tuple[int, int], num_texels: int) -> TexelGrid:
    """The `TexelGrid` of an (H, W) map held by the first H W of ``num_texels`` texels."""
    corners = offset_texels(shape, num_texels, CELL_CORNERS)
    corner_of = offset_texels(shape, num_texels, [(-di, -dj) for di, dj in CELL_CORNERS])
    return TexelGrid(to_device(np.asarray(shape, np.int32)), to_device(corners), to_device(corner_of))


class LeftOut(eqx.Module):
    """The pixels a problem over some of another's pixels leaves out
    (`pbrfit.fitting.sharding.take_pixels`), where none of them reads a texel that moves: their
    data term ``energy`` (½ Σ ||r_p||², constant while those texels are held; with the prior's
    terms of the pairs a problem over some of the texels leaves out, `take_texels`), their number
    ``pixels`` and their share ``floor`` of `rounding_floor`. With them the objective, the
    residual variance and the rounding floor are the whole problem's, so a solve over the pixels
    that move stops where one over every pixel would."""

    energy: Float[Array, ""]
    pixels: Float[Array, ""]
    floor: Float[Array, ""]


class Problem(eqx.Module):
    """One fitting problem: observations, the texels each pixel reads, which channels move.

    Attributes:
        obs: the usable pixels (`pbrfit.fitting.observations.Observations`).
        index, weight: (P, 4) texels read by each pixel and their bilinear weights.
        free: (T, K) 1 where a channel of a texel is fitted (free and observed), else 0.
        pairs: (E, 2) neighbouring texels for the smoothness prior; pair_weight (E,) 0 or 1.
        smooth: weight of the smoothness prior (0 = off).
        loss_scale: the robust loss's scale c, in image units.
        ibl: the environment's split-sum tables (``model.ibl == "split_sum"``), the pixels'
            `pbrfit.lighting.pixel_ibl.PixelIBL` (``"per_pixel"``, one row per pixel), or None.
        model, loss: static configuration.
        grid: the map the first H W texels form (`TexelGrid`, made by `texel_grid`), where each
            row's four taps are the corners of a cell of it in
            `pbrfit.fitting.observations.CELL_CORNERS` order (a `texel_layout`'s): the texels then
            pass values to and from the rows by cells (`sample_texels`, `scatter_texels`); or None.
        stencil: where the structured solver holds the Gauss-Newton matrix by stencil
            (`pbrfit.fitting.stencil`), the problem's `pbrfit.fitting.stencil.Stencil`
            (`pbrfit.fitting.stencil.with_stencil`), which needs a grid, every pixel's taps in
            one cell (`pbrfit.fitting.stencil.cells_fit`) and the prior's pairs grid neighbours;
            else None, and its products go through the pixels.
        left_out: the pixels of a larger problem this one leaves out (`LeftOut`), or None.
        texels: (M,) the texels with a free channel (indices, padded with T), which the structured
            solver's conjugate gradients run over alone where it has a stencil; None: every texel.
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
    grid: Optional[TexelGrid] = None
    stencil: object = None
    left_out: Optional[LeftOut] = None
    texels: Optional[Int[Array, " M"]] = None

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

    def left(self, name: str):
        """``left_out``'s ``name`` (energy, pixels or floor), 0 where it leaves none out."""
        return 0.0 if self.left_out is None else getattr(self.left_out, name)


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
    its row of per-pixel IBL integrals or occlusion factors, where the IBL has rows: `per_row`)."""
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
    return args + ((problem.ibl.table,) if per_row(problem.ibl) else ())


def _value_args(obs: Observations):
    """Per-pixel arguments of `_value_residual` after the radiance (each pixel's first sample row)."""
    return obs.pixel_rows(obs.exposure), obs.pixel_rows(obs.target), obs.pixel_rows(obs.residual_weight)


def _pixel_args(problem: Problem):
    """Per-row arguments of `_pixel_residual` after the material values."""
    obs = problem.obs
    return (obs.exposure, obs.target, obs.residual_weight) + _sample_args(problem)


def by_pixel(a, problem: Problem):
    """(R, ...) rows -> (P, S, ...)."""
    return a.reshape((problem.num_pixels, problem.samples) + a.shape[1:])


def _value_and_jacfwd(f, x):
    """(f(x), ∂f/∂x) by forward mode, f evaluated once."""
    jac, value = jax.jacfwd(lambda v: (f(v), f(v)), has_aux=True)(x)
    return value, jac


def sample_texels(x: Float[Array, "T K"], problem: Problem) -> Float[Array, "P K"]:
    """Bilinear samples m_p = Σ_k w_pk x_(t_pk). With a grid, by cells: each cell's four texel
    values side by side (T, 4 K), then one row of them per pixel row, from its first texel (a
    gather of P wide rows, not of 4 P narrow ones: a third of the time on a CPU)."""
    if problem.grid is None:
        return jnp.einsum("pk,pkc->pc", problem.weight, x[problem.index], precision=lax.Precision.HIGHEST)
    cells = x[problem.grid.corners].reshape(problem.num_texels, -1)
    rows = cells[problem.index[:, 0]].reshape(problem.index.shape + x.shape[1:])
    return jnp.sum(problem.weight[..., None] * rows, axis=1)


def sample_material(x: Float[Array, "T K"], problem: Problem) -> Float[Array, "P K"]:
    """The material values a pixel row shades with: `sample_texels` projected into the fit's box
    (`pbrfit.fitting.parameters.lower`, `upper`) with derivative 1, Π(m) = m + stop_gradient(clip(m) - m).

    The texels lie in the box, but their float32-weighted mix can leave it by a rounding: on a
    map held at the roughness floor, a tenth of the pixels read 0.044999998 under a floor of
    0.045, where the BRDF's floor is flat, and lost their roughness derivative (a texel kept 16%
    of its normal-matrix diagonal, and its σ was 2.7 times too large); a metallic of 1.0000001
    gave a black channel a negative radiance, which the sRGB clip flattens. The projection puts
    the value on the bound, where the clamps downstream (`pbrfit.physics.clamps.clamp_inward`) give the
    derivative from inside, and passes the derivative through."""
    m = sample_texels(x, problem)
    k = m.shape[-1]
    clipped = jnp.clip(m, jnp.asarray(lower(k), m.dtype), jnp.asarray(upper(k), m.dtype))
    return m + lax.stop_gradient(clipped - m)


def pixel_residuals(x: Float[Array, "T K"], problem: Problem) -> Float[Array, "P 3"]:
    """Every pixel's (transformed) residual at texel values x."""
    m = sample_material(x, problem)
    if problem.samples == 1:
        f = jax.vmap(lambda mm, *a: _pixel_residual(mm, *a, problem=problem))
        return f(m, *_pixel_args(problem))
    rad = jax.vmap(lambda mm, *a: _sample_radiance(mm, *a, problem=problem))(m, *_sample_args(problem))
    obs = problem.obs
    mean = jnp.mean(by_pixel(rad, problem), axis=1)
    f = jax.vmap(lambda rr, e, t, w: _value_residual(rr, e, t, w, problem))
    return f(mean, *_value_args(obs))


def smooth_residuals(x, problem: Problem):
    """The smoothness prior's residuals sqrt(smooth) (x_a - x_b) over the weighted neighbour
    pairs, in the channels the fit frees."""
    a, b = problem.pairs[:, 0], problem.pairs[:, 1]
    chan = jnp.max(problem.free, axis=0)  # channels the fit frees
    return jnp.sqrt(problem.smooth) * problem.pair_weight[:, None] * chan * (x[a] - x[b])


def residuals(x: Float[Array, "T K"], problem: Problem):
    """All residuals as a pytree (pixels, smoothness prior): E = 1/2 Σ leaves²."""
    return pixel_residuals(x, problem), smooth_residuals(x, problem)


def rounding_floor(problem: Problem) -> Float[Array, ""]:
    """½ Σ_pc (ε w_pc y_pc)², ε the float32 machine epsilon, y the targets and w their
    `Observations.residual_weight`: the data term when every residual is one rounding of its
    target. The renderer computes in float32, so below it a step's change of E is rounding, not
    evidence (a noiseless capture's fit gets there; noise of any size keeps E far above it)."""
    obs = problem.obs
    target, weight = obs.pixel_rows(obs.target), obs.pixel_rows(obs.residual_weight)
    eps = jnp.finfo(jnp.float32).eps
    return 0.5 * jnp.sum((eps * weight * target) ** 2) + problem.left("floor")


def objective(x: Float[Array, "T K"], problem: Problem) -> Float[Array, ""]:
    """E(x) = 1/2 Σ residuals² (and the term of the pixels the problem leaves out, `LeftOut`)."""
    r, s = residuals(x, problem)
    return 0.5 * (jnp.sum(r * r) + jnp.sum(s * s)) + problem.left("energy")


def linearize(x: Float[Array, "T K"], problem: Problem):
    """Residuals (P, 3), per-pixel Jacobians J_p = ∂r_p/∂m_p (P, 3, K) (per sample row,
    (R, 3, K), with several samples per pixel) and E(x)."""
    m = sample_material(x, problem)

    if problem.samples == 1:
        one = lambda mm, *a: _value_and_jacfwd(lambda v: _pixel_residual(v, *a, problem=problem), mm)  # noqa: E731
        r, jac = jax.vmap(one)(m, *_pixel_args(problem))
    else:
        r, jac = _linearize_samples(m, problem)
    s = smooth_residuals(x, problem)
    loss = 0.5 * (jnp.sum(r * r) + jnp.sum(s * s)) + problem.left("energy")
    return r, jac, loss


def _linearize_samples(m, problem: Problem):
    """Pixel residuals (P, 3) and per-sample Jacobians J_ps = ∂r_p/∂m_ps (R, 3, K): the chain
    of each sample's radiance Jacobian (forward mode, K tangents) and the Jacobian of the
    pixel's encoding and loss at the mean radiance (3 tangents), divided by S."""

    sample = lambda mm, *a: _value_and_jacfwd(lambda v: _sample_radiance(v, *a, problem=problem), mm)  # noqa: E731
    rad, jrad = jax.vmap(sample)(m, *_sample_args(problem))
    mean = jnp.mean(by_pixel(rad, problem), axis=1)
    pixel = lambda rr, e, t, w: _value_and_jacfwd(lambda v: _value_residual(v, e, t, w, problem), rr)  # noqa: E731
    r, jenc = jax.vmap(pixel)(mean, *_value_args(problem.obs))
    # by elements, not a batched dot of 3 × 3 blocks (which a CPU runs slower)
    jac = jnp.sum(jenc[:, None, :, :, None] * by_pixel(jrad, problem)[:, :, None, :, :], axis=3)
    return r, jac.reshape(jrad.shape) / problem.samples


def to_rows(a, problem: Problem):
    """(P, ...) per pixel -> (R, ...) per sample row (repeated)."""
    return a if problem.samples == 1 else jnp.repeat(a, problem.samples, axis=0)


def scatter_texels(values, problem: Problem):
    """Σ over (p, k) with t_pk = t of values[p, k] -> (T, ...). With a grid, by cells: the
    rows' four values summed onto their cells (one segment sum of P wide rows, not of 4 P narrow
    ones: a third of the time on a CPU), then each texel's from the four cells it is a corner of."""
    t = problem.num_texels
    if problem.grid is None:
        flat = values.reshape((-1,) + values.shape[2:])
        return jax.ops.segment_sum(flat, problem.index.reshape(-1), num_segments=t)
    cells = jax.ops.segment_sum(values.reshape(values.shape[0], -1), problem.index[:, 0], num_segments=t)
    cells = cells.reshape((t,) + values.shape[1:])
    of = problem.grid.corner_of
    return sum(cells[of[:, a], a] for a in range(len(CELL_CORNERS)))


def laplacian(v, problem: Problem):
    """L v, the prior's graph Laplacian over the weighted neighbour pairs (freed channels): its
    gradient and Gauss-Newton product are smooth L x and smooth L v."""
    a, b = problem.pairs[:, 0], problem.pairs[:, 1]
    chan = jnp.max(problem.free, axis=0)
    d = problem.pair_weight[:, None] * chan * (v[a] - v[b])
    t = problem.num_texels
    return jax.ops.segment_sum(d, a, num_segments=t) - jax.ops.segment_sum(d, b, num_segments=t)


def prior_degree(problem: Problem):
    """(T,) each texel's weighted neighbour count: the diagonal of the prior's L."""
    t = problem.num_texels
    w = problem.pair_weight
    return jax.ops.segment_sum(w, problem.pairs[:, 0], num_segments=t) + jax.ops.segment_sum(
        w, problem.pairs[:, 1], num_segments=t)
