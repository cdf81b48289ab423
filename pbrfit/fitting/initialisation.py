"""A per-texel starting point: grid search over (metallic, roughness) with closed-form base colour.

The objective is not convex in roughness: a texel that starts far from its highlight's width
sees almost no gradient towards it, and Levenberg-Marquardt from a constant start leaves a few
percent of texels in such basins. But for metallic fixed at 0 or 1 and a given roughness, the
outgoing radiance is affine in base colour, channel by channel (glTF BRDF: the diffuse lobe is
(1 - F) b / π with F independent of b at metallic 0; the metal lobe's F = b + (1 - b)(1 - v·h)⁵
at metallic 1), so

    L_p(b) = L_p(0) + b (L_p(1) - L_p(0)).

For every candidate (m, r) we render each pixel with its slope in b (one forward-mode pass),
solve the base colours of all texels jointly by linear least squares in linear radiance (the
targets decoded from sRGB and the tone map; `_solve_base_joint`), score the candidate by the
image-space residual (times `Observations.residual_weight`) of the pixels that read each texel,
and keep each texel's best candidate. Channels held fixed keep their values. This costs one
forward-mode render and a few conjugate-gradient iterations per candidate; the structured solver
refines from there.

The base colours are solved jointly because a pixel averages four texels: solved texel by
texel, as if each pixel showed only the texel being solved, a texel at an edge of the base
colour map takes part of its neighbour's colour, and the misfit that leaves in its pixels can
be smaller for a wrong roughness (one that shows no highlight at all) than for the true one. On
captures whose maps have sharp-edged patches this started clusters of texels in wrong basins
that neither the continuation nor the search left (tests/test_fit.py). Where normals are fitted
the start keeps the per-texel solve: it renders every candidate with flat normals, and the
joint solve then fits the bumps' shading into the base colours more closely, from where the
normals fitted worse (on tests/test_fit.py's bumpy scene, median normal error 1.48° against
0.94°, final loss 0.024 against 0.022).

That start assumes a texel's four bilinear neighbours share its candidate, which fails where
the maps change: at edges, and where one neighbour landed in a wrong roughness basin the others
then bend around. `coordinate_search` repairs this after a solve. It splits the texels into the
four parity classes (row mod 2, column mod 2); a bilinear footprint holds one texel of each, so
the texels of one class share no pixel and each can be searched over the same candidates *with
its neighbours held at their current values*: the exact conditional objective, texel by texel
(iterated conditional modes, J. Besag, "On the statistical analysis of dirty pictures", JRSS B
1986). A texel moves only if its pixels' exact residual drops. The search also tries blended
metallic values near the texel's roughness (`BLEND_METALLIC_CANDIDATES`), which the grid start
cannot represent; their base colour comes from the radiance linearised at the current one.

With several samples per pixel (`pbrfit.fitting.observations`, pixel footprints) both score each sample
against its pixel's value, as if it were a pixel of its own (cheap, and only a start); the
search still keeps a move only where the exact objective, the pixels' mean radiance, drops.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..physics.color import encode, tonemap
from ..physics.brdf import MIN_ROUGHNESS
from .observations import inverted_targets, linear_radiance
from .parameters import LOWER, UPPER
from ..render.shade import shade
from .stencil import channel_blocks, channel_product
from .objective import (Problem, objective, pixel_residuals, robust_residual, sample_texels, scatter_texels,
                        shading_normal, smooth_residuals, to_rows)

__all__ = ["ROUGHNESS_CANDIDATES", "METALLIC_CANDIDATES", "BLEND_METALLIC_CANDIDATES", "grid_initialise", "coordinate_search", "parity_classes",
           "classes_share_no_pixel"]

#: Roughness values tried per texel: geometric from the BRDF's floor to 1 (highlight widths scale
#: with alpha = r², so equal steps in log r are equal steps in highlight width). The spacing
#: matters: seen from a few directions, a texel's objective has spurious minima in roughness
#: (one off-specular sample of D is matched by two alphas) and the true basin is only about
#: ±8% of r wide on the peer scene, so a 12-value grid started a few percent of texels in
#: the wrong basin; `ROUGHNESS_RATIO` steps of 6% do not (experiments/solvers.md).
ROUGHNESS_RATIO = 1.06
ROUGHNESS_CANDIDATES = tuple(
    min(float(MIN_ROUGHNESS * ROUGHNESS_RATIO**k), 1.0) for k in range(int(np.ceil(np.log(1 / MIN_ROUGHNESS) / np.log(ROUGHNESS_RATIO))) + 1)
)
#: The coarser roughness grid of `coordinate_search`: it runs after a solve, from texels already
#: near their basin, and costs four times a full grid per sweep.
SEARCH_ROUGHNESS_RATIO = 1.25
SEARCH_ROUGHNESS_CANDIDATES = tuple(
    min(float(MIN_ROUGHNESS * SEARCH_ROUGHNESS_RATIO**k), 1.0)
    for k in range(int(np.ceil(np.log(1 / MIN_ROUGHNESS) / np.log(SEARCH_ROUGHNESS_RATIO))) + 1)
)
#: Tangent-space slopes tried per axis by `coordinate_search` when normals are fitted (tilts up
#: to atan(0.6) = 31°; the solve refines between them).
NORMAL_SEARCH_SLOPES = (-0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6)
#: Metallic values tried (the two at which radiance is affine in base colour).
METALLIC_CANDIDATES = (0.0, 1.0)
#: Blended metallic values `coordinate_search` also tries (charts, worn metal, filtered edges),
#: each at the texel's current roughness times `BLEND_ROUGHNESS_FACTORS`. Between 0 and 1 the
#: radiance is quadratic in base colour (b enters both c_diff and f0), so their base colour is
#: solved from the radiance linearised at the texel's current base colour (a Gauss-Newton step).
#: The grid start does not try them: on the peer scene a patch of dielectric texels under a
#: highlight then starts at (0.3, 0.16) instead of (0, 0.43), and the solve keeps the whole patch
#: in that basin (a patch moves together; the search moves one texel at a time). The search
#: runs from near the solution and moves a texel only where the exact energy drops.
BLEND_METALLIC_CANDIDATES = (0.25, 0.5, 0.75)
BLEND_ROUGHNESS_FACTORS = (0.8, 1.0, 1.25)
#: Floor on Σ w A² when solving a texel's base colour (a texel whose pixels see no light).
_NORMAL_FLOOR = 1e-12
#: Floor on the CG's curvature pᵀAᵀAp and on rᵀz in `_solve_base_joint`: a channel no pixel
#: constrains (all slopes 0) has both 0, and then takes steps of 0 instead of 0 / 0.
_TINY = 1e-30
#: Conjugate-gradient iterations of the grid start's joint base-colour solve per candidate
#: (`_solve_base_joint`): 3 already fit the sharp-edged conformance captures exactly; more change
#: little, as the per-texel start is close wherever the map is smooth.
GRID_BASE_CG_STEPS = 3


def _tonemap_slopes(problem: Problem, inverted):
    """(P, 3) per pixel and channel, d(tone-mapped value)/d(radiance) at the target: the tone map's
    slope (its Jacobian's diagonal) at `inverted` (`pbrfit.fitting.observations.inverted_targets`),
    times 2^exposure; None without a tone map. The grid start weights its base-colour least squares by it, which makes them a
    linearised fit of the tone-mapped values: near the top of the display range a tone map is
    flat, one 8-bit code there spans a large range of radiance, and unweighted, those few pixels
    decided whole texels' base colours."""
    obs = problem.obs
    if obs.tonemap == "none":
        return None
    x = inverted
    diag = [jax.jvp(lambda v: tonemap(v, obs.tonemap), (x,), (jnp.zeros_like(x).at[:, c].set(1.0),))[1][:, c]
            for c in range(3)]
    return jnp.stack(diag, axis=1) * jnp.exp2(obs.exposure)[:, None]


def _candidates(roughness, dtype, metallic=METALLIC_CANDIDATES) -> jnp.ndarray:
    """(C, 2) (metallic, roughness) pairs: `metallic` × `roughness` (clipped to bounds)."""
    metals = jnp.asarray(metallic, dtype)
    roughs = jnp.clip(jnp.asarray(roughness, dtype), LOWER[4], UPPER[4])
    mm, rr = jnp.meshgrid(metals, roughs, indexing="ij")
    return jnp.stack([mm.reshape(-1), rr.reshape(-1)], axis=1)


def _shaded_once(problem: Problem, *arrays):
    """``arrays`` (a candidate's radiance and its slope in base colour), computed once and stored
    where the environment is lit by the split sum; as they are elsewhere.

    XLA's CPU backend fuses an elementwise producer into each of its consumers, so each use of
    the shaded rows (the base-colour sums, the linear model at base colour 0, the residuals)
    shaded them again, and a use broadcast over a row's four bilinear taps four times. The split
    sum's shading is dear (prefiltered and irradiance lookups), so there the rows pass through a
    conditional, which XLA neither fuses across nor removes: its predicate is true for every
    value, NaN included, but the compiler cannot know it. On `sphere-env` the search took 2.0 s
    instead of 4.0 and the grid start 1.2 instead of 2.2. Under punctual lights alone the fused
    programs are faster (the peer's search 0.67 to 0.75 s against 0.81 to 0.84 stored), with
    per-pixel integrals as fast (experiments/speed.md, "The shading computed once")."""
    if problem.model.ibl != "split_sum" or arrays[0].size == 0:
        return arrays
    v = arrays[0].ravel()[0]
    return jax.lax.cond((v == v) | jnp.isnan(v), lambda: arrays, lambda: tuple(jnp.zeros_like(a) for a in arrays))


def _solve_base(l0, a, y, weight, problem: Problem):
    """(T, 3) per-texel base colour b minimising Σ_pk weight_pk ||y_p - l0_p - b a_p||² channel by
    channel (linear radiance L_p = l0_p + b a_p), clipped to [0, 1]."""
    return jnp.clip(_per_texel_base(l0, a, y, weight, problem), 0.0, 1.0)


def _per_texel_base(l0, a, y, weight, problem: Problem, num=None):
    """`_solve_base` before clipping: Σ w a (y - l0) / Σ w a² per texel and channel (`num`, the
    numerator, when already scattered)."""
    w = weight[:, :, None]
    if num is None:
        num = scatter_texels(w * (a * (y - l0))[:, None, :], problem)
    den = scatter_texels(w * (a * a)[:, None, :], problem)
    return num / jnp.maximum(den, _NORMAL_FLOOR)


def _solve_base_joint(l0, a, y, problem: Problem, steps: Optional[int] = None, blocks=None):
    """(T, 3) base colours b of all texels minimising Σ_p ||y_p - l0_p - a_p Σ_k w_pk b_(t_pk)||²
    channel by channel (every pixel's bilinear mix of its texels; linear radiance), clipped to
    [0, 1]: `steps` iterations of Jacobi-preconditioned conjugate gradients on the normal
    equations AᵀA b = Aᵀ(y - l0), (A b)_p = a_p Σ_k w_pk b_(t_pk), started from the unclipped
    per-texel solution Aᵀ(y - l0) / (AᵀA 1) (`_per_texel_base`: the row sums of AᵀA are
    Σ_p w_pt a_p², as a pixel's bilinear weights sum to 1). `steps` defaults to
    `GRID_BASE_CG_STEPS`, read when the grid start is traced.

    Where the problem has a stencil (``Problem.stencil``, at pixel centres) AᵀA is assembled by
    it once (`pbrfit.fitting.stencil.channel_blocks`) and each product is a gather of 9 texels:
    on the peer scene the grid start took 290 ms against 480 through the pixels, where each
    product is a gather and a scatter of every pixel's taps (the preconditioner there is
    Σ_pk w_pk² a_p², the diagonal where a pixel's taps read distinct texels). ``blocks``: that
    AᵀA by stencil, when the caller has it (`_slope_blocks_shared`)."""
    steps = GRID_BASE_CG_STEPS if steps is None else steps
    w = problem.weight[:, :, None]
    rhs = scatter_texels(w * (a * (y - l0))[:, None, :], problem)  # also the per-texel solve's numerator
    if _by_stencil(problem):
        st = problem.stencil
        blocks = channel_blocks(a * a, problem, st) if blocks is None else blocks

        def normal_op(b):  # AᵀA b
            return channel_product(blocks, st.neighbours, b)

        diag = jnp.maximum(blocks[:, st.centre], _NORMAL_FLOOR)
        b = rhs / jnp.maximum(jnp.sum(blocks, axis=1), _NORMAL_FLOOR)
    else:
        def normal_op(b):  # AᵀA b
            return scatter_texels(w * (a * a * sample_texels(b, problem))[:, None, :], problem)

        diag = jnp.maximum(scatter_texels(w * w * (a * a)[:, None, :], problem), _NORMAL_FLOOR)
        b = _per_texel_base(l0, a, y, problem.weight, problem, num=rhs)
    r = rhs - normal_op(b)
    z = r / diag
    p, rz = z, jnp.sum(r * z, axis=0)
    for _ in range(steps):  # a handful, unrolled: per channel, α and β are scalars
        q = normal_op(p)
        alpha = rz / jnp.maximum(jnp.sum(p * q, axis=0), _TINY)
        b, r = b + alpha * p, r - alpha * q
        z = r / diag
        rz_new = jnp.sum(r * z, axis=0)
        p, rz = z + (rz_new / jnp.maximum(rz, _TINY)) * p, rz_new
    return jnp.clip(b, 0.0, 1.0)


def _by_stencil(problem: Problem) -> bool:
    """Whether `_solve_base_joint` assembles AᵀA by stencil (at pixel centres, with a stencil)."""
    return problem.stencil is not None and problem.samples == 1


def _slope_blocks_shared(problem: Problem) -> bool:
    """Whether the grid start's candidates at metallic 0 share one AᵀA (`_solve_base_joint`): by
    stencil, under punctual lights alone, with a diffuse lobe that does not depend on roughness
    (Lambert's, or none). There a pixel's slope in base colour is the diffuse lobe's,
    (1 - F(v·h)) / π Σ_l E_l (n·l_l) with F at the dielectric f0: the specular lobe's F D V enters
    only through f0 = mix(0.04, b, metallic), whose slope in b is metallic, 0. So the slope, and
    AᵀA, are the same at every roughness: the first candidate at metallic 0 assembles it (half
    of a candidate's time at 512² maps) and the others take it."""
    return _by_stencil(problem) and problem.model.ibl is None and problem.model.diffuse in ("lambert", "none")


def _best_candidates(candidate, cands, memo=None):
    """Per texel, the first of the candidates ``cands`` (C, ...) whose score is least (a NaN score
    counting as least, as `jnp.argmin` reads it) and its base colour: (index (T,), base (T, 3)),
    ``candidate(row)`` giving every texel's (base (T, 3), score (T,)) for one row. Scored one
    candidate at a time and the best kept as they go, not all candidates' base colours stacked
    and then chosen from: (C, T, 3) floats, 350 MB for the grid start's 110 candidates on a 512²
    map. With ``memo`` (arrays) ``candidate(row, memo)`` also returns the memo the next row gets."""
    def keep(best, row_k):
        row, k = row_k
        index, base, score, kept = best
        b, s, kept = (candidate(row) + (None,)) if memo is None else candidate(row, kept)
        better = (k == 0) | (s < score) | (jnp.isnan(s) & ~jnp.isnan(score))
        kept_best = (jnp.where(better, k, index), jnp.where(better[:, None], b, base), jnp.where(better, s, score))
        return kept_best + (kept,), None

    shapes = jax.eval_shape(candidate, cands[0], *(() if memo is None else (memo,)))
    start = (jnp.zeros(shapes[1].shape, jnp.int32), jnp.zeros(shapes[0].shape, shapes[0].dtype),
             jnp.zeros(shapes[1].shape, shapes[1].dtype), memo)
    (index, base, _, _), _ = jax.lax.scan(keep, start, (cands, jnp.arange(cands.shape[0], dtype=jnp.int32)))
    return index, base


@eqx.filter_jit
def grid_initialise(x_fixed, problem: Problem):
    """(T, K) starting values: each observed texel's best (metallic, roughness) candidate with its
    closed-form base colour; channels that are not free keep `x_fixed`."""
    obs = problem.obs
    free = problem.free
    seen = jnp.max(free, axis=1) > 0
    fixed_m = sample_texels(x_fixed, problem)  # (P, 5) sampled values of the fixed channels
    inverted = inverted_targets(obs)
    y = linear_radiance(obs, inverted)
    slope = _tonemap_slopes(problem, inverted)
    metal_free = jnp.max(free[:, 3]) > 0
    rough_free = jnp.max(free[:, 4]) > 0
    base_free = jnp.max(free[:, 0]) > 0
    normal = shading_normal(fixed_m, obs.normal, obs.tangent)

    per_texel = x_fixed.shape[1] > 5  # normals fitted: see the module docstring
    sharing = not per_texel and _slope_blocks_shared(problem)

    def candidate(metal, rough, memo=None):
        m_p = jnp.where(metal_free, metal, fixed_m[:, 3:4])
        r_p = jnp.where(rough_free, rough, fixed_m[:, 4:5])

        def render(b):
            return shade(normal, obs.view, obs.light_l, obs.light_radiance, b, m_p, r_p, problem.model, problem.ibl)

        zero = jnp.zeros_like(fixed_m[:, :3])
        # affine in b: the slope is exact
        l0, a = _shaded_once(problem, *jax.jvp(render, (zero,), (jnp.ones_like(zero),)))
        # with a tone map, least squares in (linearised) tone-mapped values: the rows times its slope
        lw, aw, yw = (l0, a, y) if slope is None else (l0 * slope, a * slope, y * slope)
        if per_texel:
            base_t = _solve_base(lw, aw, yw, problem.weight, problem)
        elif not sharing:
            base_t = _solve_base_joint(lw, aw, yw, problem)
        else:  # every pixel at metallic 0: AᵀA as the first such candidate assembled it (memo)
            blocks, done = memo
            at_0 = jnp.all(m_p == 0)
            blocks = jax.lax.cond(at_0 & done, lambda: blocks,
                                  lambda: channel_blocks(aw * aw, problem, problem.stencil))
            memo = (blocks, done | at_0)
            base_t = _solve_base_joint(lw, aw, yw, problem, blocks=blocks)
        base_t = jnp.where(base_free, base_t, x_fixed[:, :3])
        b_p = sample_texels(jnp.concatenate([base_t, x_fixed[:, 3:]], axis=1), problem)[:, :3]
        value = encode(l0 + b_p * a, obs.exposure[:, None], obs.tonemap, obs.color_space)
        err = jnp.sum(((value - obs.target) * obs.residual_weight) ** 2, axis=1)
        score = scatter_texels((problem.weight * err[:, None])[:, :, None], problem)[:, 0]
        return (base_t, score) + ((memo,) if sharing else ())

    cands = _candidates(ROUGHNESS_CANDIDATES, x_fixed.dtype)
    if sharing:
        blocks = jax.eval_shape(lambda a: channel_blocks(a, problem, problem.stencil), obs.target)
        memo = (jnp.zeros(blocks.shape, blocks.dtype), jnp.asarray(False))
        best, base = _best_candidates(lambda mr, memo: candidate(mr[0], mr[1], memo), cands, memo)
    else:
        best, base = _best_candidates(lambda mr: candidate(mr[0], mr[1]), cands)
    x = jnp.concatenate([base, cands[best], x_fixed[:, 5:]], axis=1)
    x = jnp.where(free > 0, x, x_fixed)
    return jnp.where(seen[:, None], x, x_fixed)


def parity_classes(shape: tuple[int, int]) -> np.ndarray:
    """(T,) int32 class of each texel of (H, W) maps: 2 (row mod 2) + (column mod 2)."""
    h, w = shape
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return (2 * (rows % 2) + (cols % 2)).reshape(-1).astype(np.int32)


def _texel_scores(err, problem: Problem):
    """(T,) Σ of the errors of the pixels that read each texel (with nonzero weight)."""
    reads = (problem.weight > 0).astype(err.dtype)
    return scatter_texels((reads * err[:, None])[:, :, None], problem)[:, 0]


def _pair_scores(pair, problem: Problem):
    """(T,) Σ of the pair energies `pair` (E,) of the smoothness pairs each texel is in."""
    t = problem.num_texels
    return jax.ops.segment_sum(pair, problem.pairs[:, 0], num_segments=t) + jax.ops.segment_sum(
        pair, problem.pairs[:, 1], num_segments=t)


def _prior_scores(x, problem: Problem):
    """(T,) Σ of the squared smoothness-prior residuals of the pairs each texel is in."""
    s = smooth_residuals(x, problem)
    return _pair_scores(jnp.sum(s * s, axis=1), problem)


def _energies(x, problem: Problem):
    """(T,) local energies and the whole objective E(x), from one evaluation of the residuals.

    A texel's local energy is the part of the objective that depends on it: the squared
    (robust) residuals of the pixels that read it plus its smoothness-prior pairs. Exact for
    texels that share no pixel and no pair (one parity class; with several samples per pixel,
    texels two apart can share a pixel, and `coordinate_search` checks the whole objective)."""
    r = pixel_residuals(x, problem)
    s = smooth_residuals(x, problem)
    err = jnp.sum(r * r, axis=1)
    pair = jnp.sum(s * s, axis=1)
    # with several samples per pixel, a pixel's error counts once per sample reading the texel
    local = _texel_scores(to_rows(err, problem), problem)
    return local + _pair_scores(pair, problem), 0.5 * (jnp.sum(err) + jnp.sum(pair)) + problem.left("energy")


def _local_energy(x, problem: Problem):
    """(T,) the local energies of `_energies`."""
    return _energies(x, problem)[0]


def classes_share_no_pixel(problem: Problem, classes: np.ndarray) -> bool:
    """Whether no pixel reads two texels of one class (`classes` (T,), host-side) with nonzero
    weight: then the texels of a class have separable local energies (`_energies`), and
    `coordinate_search` needs no check of the whole objective. False where a pixel's samples read
    two cells (several samples per pixel), or on an odd-sized map whose wrapped seam puts two
    texels of a class in one cell."""
    index = np.asarray(problem.index).reshape(problem.num_pixels, -1)
    valid = np.asarray(problem.weight).reshape(problem.num_pixels, -1) > 0
    cls = np.asarray(classes)[index]
    for c in np.unique(cls[valid]):
        member = valid & (cls == c)
        low = np.where(member, index, np.iinfo(index.dtype).max).min(axis=1)
        high = np.where(member, index, -1).max(axis=1)
        if np.any((high >= 0) & (low != high)):
            return False
    return True


def _normal_search(x, problem: Problem, member):
    """One parity class's texels (`member` (T, 2): their free slope channels) try every
    (s_x, s_y) of `NORMAL_SEARCH_SLOPES`² with their other channels kept, scored by the exact
    local energy; a texel moves only where the energy drops."""
    slopes = jnp.asarray(NORMAL_SEARCH_SLOPES, x.dtype)
    sx, sy = jnp.meshgrid(slopes, slopes, indexing="ij")
    cands = jnp.stack([sx.reshape(-1), sy.reshape(-1)], axis=1)

    def with_slopes(s):
        return x.at[:, 5:].set(jnp.where(member, s, x[:, 5:]))

    energies = jax.lax.map(lambda s: _local_energy(with_slopes(s), problem), cands)  # (C, T)
    best = jnp.argmin(energies, axis=0)
    proposal = x.at[:, 5:].set(jnp.where(member, cands[best], x[:, 5:]))
    better = jnp.min(energies, axis=0) < _local_energy(x, problem)
    return jnp.where(better[:, None], proposal, x)


@eqx.filter_jit
def coordinate_search(x, problem: Problem, classes, rounds=1, blend: bool = True, separable: bool = False):
    """Per-texel grid search with neighbours held fixed, one parity class at a time.

    For class c, every texel t of the class tries each (metallic, roughness) candidate with its
    base colour in closed form (radiance is affine in t's base colour for a fixed sampled
    metallic: one forward-mode render per candidate), while every texel of other classes keeps
    its value. With `blend` (static) it also tries `BLEND_METALLIC_CANDIDATES` near the texel's
    roughness (pass False when metallic is fixed: they would repeat the grid).
    Each pixel reads at most one texel of the class, so a texel's score, the summed squared
    error of the pixels that read it, depends on its own value only. The best candidate is then
    checked against the exact local energy (robust loss and smoothness prior included) and kept
    only where it lowers it, so the objective never rises (the current and proposed values'
    local energies come from one batched evaluation). When normals are fitted, the class's
    texels then try the slopes of `NORMAL_SEARCH_SLOPES` the same way (other channels kept).
    Where a pixel may read two texels of a class the local energies do not add up, and each
    sweep checks the whole objective too; `separable` (static,
    `classes_share_no_pixel`) says it need not (one evaluation of the pixels less per sweep,
    and in the program).
    `rounds` sweeps over the four classes; the fit passes it as an int32 array (a Python int is
    static), so its search and its repair share one executable. `classes` is `parity_classes(shape)` (T,); channels that are
    not free keep x.
    """
    obs = problem.obs
    free = problem.free
    y = linear_radiance(obs)
    metal_free = free[:, 3:4] > 0
    rough_free = free[:, 4:5] > 0
    base_free = free[:, 0:3] > 0
    # rows (metallic, roughness or factor, relative): the grid, then the blends relative to x
    cands = _candidates(SEARCH_ROUGHNESS_CANDIDATES, x.dtype)
    cands = jnp.concatenate([cands, jnp.zeros_like(cands[:, :1])], axis=1)
    if blend and BLEND_METALLIC_CANDIDATES:
        mm, ff = np.meshgrid(BLEND_METALLIC_CANDIDATES, BLEND_ROUGHNESS_FACTORS, indexing="ij")
        blends = np.stack([mm.reshape(-1), ff.reshape(-1), np.ones(mm.size)], axis=1)
        cands = jnp.concatenate([cands, jnp.asarray(blends, x.dtype)])
    reads = (problem.weight > 0).astype(x.dtype)

    def sweep(x, c):
        member = (classes == c)[:, None] & (jnp.max(free, axis=1, keepdims=True) > 0)
        # the search keeps normals: the shading normals are those of x
        normal = shading_normal(sample_texels(x, problem), obs.normal, obs.tangent)

        def trial(metal, rough, base):
            """x with class texels set to (base, metal, rough) where free (normals kept)."""
            t = jnp.concatenate([base, jnp.broadcast_to(metal, base.shape[:1] + (1,)),
                                 jnp.broadcast_to(rough, base.shape[:1] + (1,)), x[:, 5:]], axis=1)
            t = jnp.where(jnp.concatenate([base_free, metal_free, rough_free, free[:, 5:] > 0], axis=1), t, x)
            return jnp.where(member, t, x)

        def render(xx):
            m = sample_texels(xx, problem)
            return shade(normal, obs.view, obs.light_l, obs.light_radiance, m[:, 0:3], m[:, 3:4], m[:, 4:5],
                         problem.model, problem.ibl)

        # per pixel and channel: the bilinear weight of the class texel whose base colour moves
        moving = (member & base_free).astype(x.dtype)
        share = sample_texels(moving, problem)

        def class_value(base_t):
            """Per pixel: the base colour of the class texel the pixel reads (0 where none)."""
            return jnp.where(share > 0, sample_texels(moving * base_t, problem) / jnp.where(share > 0, share, 1.0), 0.0)

        def roughness(row):
            """(T, 1) the row's roughness: absolute, or a factor on each texel's current one."""
            r = jnp.where(row[2] > 0, x[:, 4:5] * row[1], row[1])
            return jnp.clip(r, LOWER[4], UPPER[4])

        def candidate(row):
            # the radiance and its slope in the class texels' base colour, linearised at their
            # current base colour (one forward-mode pass): exact where the radiance is affine in
            # it (metallic 0 or 1 throughout the footprint), a Gauss-Newton step elsewhere
            rough = roughness(row)
            b0 = x[:, :3]
            lb, a = _shaded_once(problem, *jax.jvp(lambda b: render(trial(row[0], rough, b)), (b0,),
                                                   (jnp.ones_like(b0),)))
            l0 = lb - class_value(b0) * a  # the linear model at class base colour 0
            base_t = jnp.where(base_free, _solve_base(l0, a, y, reads, problem), x[:, :3])
            # the linear model's prediction at the solved base colour: a is the slope per unit of
            # the class texel's base colour, times its weight `share`
            xb = trial(row[0], rough, base_t)
            value = encode(l0 + class_value(base_t) * a, obs.exposure[:, None], obs.tonemap, obs.color_space)
            resid = robust_residual((value - obs.target) * obs.residual_weight, problem.loss, problem.loss_scale)
            return base_t, _texel_scores(jnp.sum(resid * resid, axis=1), problem) + _prior_scores(xb, problem)

        best, base = _best_candidates(candidate, cands)
        proposal = trial(cands[best, 0][:, None], roughness(cands[best].T[:, :, None]), base)
        local, energy = jax.vmap(lambda xx: _energies(xx, problem))(jnp.stack([x, proposal]))
        keep = member & (local[1] < local[0])[:, None]
        new = jnp.where(keep, proposal, x)
        if x.shape[1] > 5:
            new = _normal_search(new, problem, member & (free[:, 5:] > 0))
        if separable:
            return new, None
        return jnp.where(objective(new, problem) <= energy[0], new, x), None

    return jax.lax.fori_loop(0, 4 * rounds, lambda i, x: sweep(x, i % 4)[0], x)
