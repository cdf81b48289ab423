"""The Gauss-Newton matrix by stencil: JᵀJ + smooth L held as K × K blocks between each texel and
the texels around it, so that its products do not go through the pixels.

A pixel's residual depends on the texels its taps read (`pbrfit.fitting.objective`): at pixel
centres the four of its bilinear sample, the corners of a 2 × 2 cell of the map; with S samples
per pixel the taps of all of them, which straddle a texel centre wherever the samples do, and lie
in a 3 × 3 cell while the pixel is narrower than a texel. With every pixel's taps in a cell of
side c (`cell_side`), a texel shares pixels only with texels less than c away along each axis,
and JᵀJ is (2c - 1)² blocks per texel, 9 or 25 (`offsets`): with cells named by their first
corner and o_a the offset of corner a,

    (JᵀJ)_(t, t + o) = Σ_(a, b: o_b - o_a = o) C_(t - o_a),ab,    C_c,ab = Σ_(p in cell c) B_paᵀ B_pb,

where B_pa = Σ_(taps j of p on corner a) w_j J_(p,s_j) is pixel p's 3 × K Jacobian towards corner
a (w_pa J_p at pixel centres; taps on one texel add up, so clamped edges are exact too).
`stencil_blocks` assembles it once per solver step (a segment sum over the pixels' cells per
corner pair, 10 or 45 of them, then a gather per pair, and the prior's smooth L, whose pairs are
grid neighbours); a product (`stencil_product`) is then a gather of each texel's neighbours and
their K × K products, with no gather, product and scatter per pixel row as
`pbrfit.fitting.normal_matrix.gn_product` has (on the peer scene, 4096 texels read by 60k
pixels, 0.5 ms against 3.3 ms on a CPU).

Offsets wrap around the map (the "repeat" sampler reads it so; clamped taps never wrap), and all
of it is modular arithmetic on the map's (H, W), which the problem carries as an array
(`pbrfit.fitting.objective.Problem.grid`): one compiled program serves every level of a fit. On a
map narrower than the stencil several offsets reach one texel; each pair of taps is kept at one of
them, and the product is the same. Whether every pixel's taps fit a cell is checked on the host
when the problem is made (`cells_fit`); where one does not (a pixel wider than a texel), the
problem has no grid and the solver's products go through the pixels.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int

from .normal_matrix import block_gram, gauss_newton_factors, gn_product, normal_blocks
from .objective import Problem, by_pixel, prior_degree

__all__ = ["Stencil", "cell_side", "offsets", "cells_fit", "stencil", "stencil_blocks", "stencil_product", "channel_blocks",
           "channel_product", "gauss_newton_operator"]

#: A grid step beyond every stencil (its cell cannot hold the pixel).
_FAR = 1 << 20


def cell_side(samples: int) -> int:
    """The side of the cell that holds a pixel's taps: 2 at pixel centres (one bilinear sample),
    3 with several samples per pixel."""
    return 2 if samples == 1 else 3


def offsets(side: int) -> tuple[tuple[int, int], ...]:
    """The (di, dj) of the stencil of cells of `side`: (2 side - 1)² of them, row by row; the
    middle one, (0, 0), is the texel itself."""
    r = side - 1
    return tuple((di, dj) for di in range(-r, r + 1) for dj in range(-r, r + 1))


def _slot(di, dj, side: int):
    """The place of offset (di, dj) in `offsets` (side)."""
    r = side - 1
    return (2 * r + 1) * (di + r) + (dj + r)


def _steps(d, n, side: int, xp=jnp):
    """Differences d of grid coordinates on a ring of n as steps in [-(side - 1), side - 1] that
    lead there (the positive one where two do), `_FAR` where none does."""
    d = xp.mod(d, n)
    r = side - 1
    return xp.where(d <= r, d, xp.where(d >= n - r, d - n, _FAR))


def cells_fit(index, samples: int, shape: tuple[int, int]) -> bool:
    """Whether the taps of every pixel (``index`` (R, 4), `samples` rows a pixel, host arrays) lie
    in one cell of side `cell_side` of the ``shape`` map (wrapped), as `stencil_blocks` needs."""
    h, w = shape
    side = cell_side(samples)
    index = np.asarray(index).reshape(-1, 4 * samples)
    for coord, n in ((index // w, h), (index % w, w)):
        steps = _steps(coord - coord[:, :1], n, side, np)
        if np.any(steps.max(axis=1) - steps.min(axis=1) > side - 1):
            return False
    return True


class Stencil(eqx.Module):
    """Where a problem's texels and pixels sit on its map (`stencil`): each texel's neighbour at
    every offset of `offsets` (T, N), N = (2 side - 1)²; each pixel's cell, the texel of its first corner (P,);
    the bilinear weights of each sample's taps summed per corner of the cell (P, S, side²); and the
    offset of each prior pair's second texel from its first, and back (E, 2)."""

    neighbours: Int[Array, "T N"]
    cell: Int[Array, " P"]
    share: Float[Array, "P S C"]
    pair_offsets: Int[Array, "E 2"]

    @property
    def side(self) -> int:
        return int(round(self.share.shape[-1] ** 0.5))

    @property
    def centre(self) -> int:
        """The place of the texel itself among its neighbours (its diagonal block)."""
        return self.neighbours.shape[1] // 2


def stencil(problem: Problem) -> Stencil:
    """The `Stencil` of ``problem`` on its ``grid`` (each pixel's taps in one cell: `cells_fit`).
    A pixel's cell starts at the smallest row and column among its taps (wrapped). A texel past
    H W (a coarser level's padding) is its own neighbour at every offset: no pixel reads it, and
    its blocks are zero."""
    h, w = problem.grid[0], problem.grid[1]
    side = cell_side(problem.samples)
    t = jnp.arange(problem.num_texels, dtype=problem.grid.dtype)
    di, dj = (jnp.asarray([o[n] for o in offsets(side)], t.dtype) for n in (0, 1))
    neighbours = jnp.mod(t[:, None] // w + di, h) * w + jnp.mod(t[:, None] % w + dj, w)
    neighbours = jnp.where(t[:, None] < h * w, neighbours, t[:, None])
    p, samples = problem.num_pixels, problem.samples
    index = problem.index.reshape(p, 4 * samples)
    row, col = index // w, index % w
    sr, sc = _steps(row - row[:, :1], h, side), _steps(col - col[:, :1], w, side)
    low_r, low_c = jnp.min(sr, axis=1, keepdims=True), jnp.min(sc, axis=1, keepdims=True)
    cell = jnp.mod(row[:, 0] + low_r[:, 0], h) * w + jnp.mod(col[:, 0] + low_c[:, 0], w)
    corner = side * (sr - low_r) + (sc - low_c)
    weight = problem.weight.reshape(p, 4 * samples, 1)
    share = weight * (corner[..., None] == jnp.arange(side * side)).astype(weight.dtype)
    a, b = problem.pairs[:, 0], problem.pairs[:, 1]
    pi, pj = _steps(b // w - a // w, h, side), _steps(b % w - a % w, w, side)
    pair_offsets = jnp.stack([_slot(pi, pj, side), _slot(-pi, -pj, side)], axis=1)
    return Stencil(neighbours, cell, jnp.sum(share.reshape(p, samples, 4, -1), axis=2), pair_offsets)


def stencil_blocks(jac: Float[Array, "R 3 K"], problem: Problem, st: Stencil) -> Float[Array, "T N K K"]:
    """JᵀJ + smooth L by stencil (module docstring): block n of texel t is the K × K block between
    t and ``st.neighbours[t, n]``, ``st`` the problem's `stencil`. The prior adds
    smooth w (e_a - e_b)(e_a - e_b)ᵀ ⊗ diag(freed channels) for each pair (a, b) of weight w."""
    t = problem.num_texels
    pairs = _corner_pairs(st.side)
    # by elements (`block_gram`; the flash scene's 2 × 2 samples: 184 ms an assembly against 464)
    if problem.samples == 1:
        gp = block_gram(jac, jac)

        def pair_rows(a, b):  # w_pa w_pb J_pᵀJ_p
            return (st.share[:, 0, a] * st.share[:, 0, b])[:, None, None] * gp
    else:
        jb = jnp.sum(st.share[:, :, :, None, None] * by_pixel(jac, problem)[:, :, None], axis=1)  # (P, c², 3, K)

        def pair_rows(a, b):  # B_paᵀ B_pb
            return block_gram(jb[:, a], jb[:, b])

    # a scan step per corner pair: the rows of all pairs at once make a buffer (over 32 MiB for
    # 60k pixels) that the allocator maps afresh at each call, and took five times as long
    _, cells = lax.scan(lambda _, ab: (None, jax.ops.segment_sum(pair_rows(ab[0], ab[1]), st.cell, num_segments=t)),
                        None, jnp.asarray(np.asarray(pairs, np.int32)))  # (pairs, T, K, K)
    blocks = _by_offset(cells, st, lambda block: jnp.swapaxes(block, 1, 2))
    a, b = problem.pairs[:, 0], problem.pairs[:, 1]
    sw = problem.smooth * problem.pair_weight
    n = st.neighbours.shape[1]
    at = jnp.concatenate([a * n + st.centre, b * n + st.centre, a * n + st.pair_offsets[:, 0],
                          b * n + st.pair_offsets[:, 1]])
    prior = jax.ops.segment_sum(jnp.concatenate([sw, sw, -sw, -sw]), at, num_segments=t * n).reshape(t, n)
    return blocks + prior[:, :, None, None] * jnp.diag(jnp.max(problem.free, axis=0))


def _corner_pairs(side: int) -> list[tuple[int, int]]:
    """The cell's corner pairs (a, b), a <= b, corners numbered row by row."""
    return [(a, b) for a in range(side * side) for b in range(a, side * side)]


def _by_offset(cells, st: Stencil, transpose):
    """(T, N, ...) the stencil's blocks from the cells' sums per corner pair, ``cells[q]`` (T, ...)
    for the q-th pair of `_corner_pairs`: block (t, t + o) adds pair (a, b)'s sum over the cell t
    is corner a of, for o_b - o_a = o, and ``transpose`` of it for the pair the other way round."""
    side = st.side
    corners = [(i, j) for i in range(side) for j in range(side)]
    slots = [[] for _ in range(st.neighbours.shape[1])]
    for q, (qa, qb) in enumerate(_corner_pairs(side)):
        for a, b, flip in ((qa, qb, False), (qb, qa, True))[: 1 if qa == qb else 2]:
            (ai, aj), (bi, bj) = corners[a], corners[b]
            back = _slot(-ai, -aj, side)  # texel t is corner a of cell t - o_a
            block = cells[q] if back == st.centre else cells[q][st.neighbours[:, back]]
            slots[_slot(bi - ai, bj - aj, side)].append(transpose(block) if flip else block)
    zero = jnp.zeros_like(cells[0])
    return jnp.stack([sum(s) if s else zero for s in slots], axis=1)


def channel_blocks(rows: Float[Array, "P C"], problem: Problem, st: Stencil) -> Float[Array, "T N C"]:
    """By stencil, the Gram matrix of a problem at pixel centres whose parameters are one value
    per texel and channel and whose residual channel c reads channel c alone, scaled by
    ``rows[p, c]`` (its squared slope): entry (t, u, c) = Σ_p rows_pc w_pt w_pu, block n of texel t
    the one towards ``st.neighbours[t, n]``. One segment sum of every corner pair's rows (wide
    rows; `stencil_blocks` takes K × K blocks a pair at a time). At pixel centres only (one
    sample: the cells of side 2)."""
    pairs = _corner_pairs(st.side)
    share = st.share[:, 0, :]
    per_pair = jnp.stack([share[:, a] * share[:, b] for a, b in pairs], axis=1)[:, :, None] * rows[:, None, :]
    cells = jax.ops.segment_sum(per_pair.reshape(per_pair.shape[0], -1), st.cell, num_segments=problem.num_texels)
    cells = jnp.moveaxis(cells.reshape(problem.num_texels, len(pairs), -1), 1, 0)  # (pairs, T, C)
    return _by_offset(cells, st, lambda block: block)


def channel_product(blocks: Float[Array, "T N C"], neighbours: Int[Array, "T N"], v: Float[Array, "T C"]):
    """(Σ_n blocks[t, n] v[neighbours[t, n]])_t per channel: the product of `channel_blocks`."""
    return jnp.sum(blocks * v[neighbours], axis=1)


def stencil_product(blocks: Float[Array, "T N K K"], neighbours: Int[Array, "T N"], v: Float[Array, "T K"]):
    """(Σ_n blocks[t, n] v[neighbours[t, n]])_t, the product of a matrix held by stencil: products
    and sums of float32 elements (no dot, so no TF32 on a GPU), which a CPU runs three times as
    fast as a batched dot of K × K blocks."""
    return jnp.sum(blocks * v[neighbours][:, :, None, :], axis=(1, 3))


def gauss_newton_operator(jac: Float[Array, "R 3 K"], problem: Problem, st: Optional[Stencil]):
    """JᵀJ + smooth L at the per-row Jacobians ``jac``, as the solvers use it: (its diagonal
    blocks (T, K, K), the product v ↦ (JᵀJ + smooth L) v, and its blocks by stencil (T, N, K, K)).
    By stencil where ``st`` (the problem's `stencil`) is given, else through the pixels
    (`pbrfit.fitting.normal_matrix.gn_product`; no stencil blocks then, None)."""
    if st is None:
        gp = gauss_newton_factors(jac, problem)
        eye = jnp.eye(jac.shape[-1], dtype=jac.dtype)
        blocks = normal_blocks(jac, problem) + problem.smooth * prior_degree(problem)[:, None, None] * eye
        return blocks, lambda v: gn_product(gp, v, problem), None
    full = stencil_blocks(jac, problem, st)
    return full[:, st.centre], lambda v: stencil_product(full, st.neighbours, v), full
