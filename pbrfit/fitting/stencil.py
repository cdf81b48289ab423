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
`stencil_blocks` assembles it once per iterate of the solver (a segment sum over the pixels' cells per
corner pair, 10 or 45 of them, then a gather per pair, and the prior's smooth L, whose pairs are
grid neighbours); a product (`stencil_product`) is then a gather of each texel's neighbours and
their K × K products, with no gather, product and scatter per pixel row as
`pbrfit.fitting.normal_matrix.gn_product` has (on the peer scene, 4096 texels read by 60k
pixels, 0.5 ms against 3.3 ms on a CPU).

Offsets wrap around the map (the "repeat" sampler reads it so; clamped taps never wrap). Where
each texel's neighbours and each pixel's cell and corner weights are (`Stencil`) is worked out on
the host when the problem is made (`with_stencil`) and travels with it as arrays
(``Problem.stencil``), so one compiled program serves every level of a fit, and the programs hold
no copy of that index arithmetic (it was 9 to 15 kernels in each of the solver's, the grid
start's and the uniform check's programs). On a map narrower than the stencil several offsets
reach one texel; each pair of taps is kept at one of them, and the product is the same. Where a
pixel's taps do not fit a cell (`cells_fit`: a pixel wider than a texel), the problem has no
stencil and the solver's products go through the pixels.
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

from .normal_matrix import (NEIGHBOUR_OFFSETS, block_gram, gauss_newton_factors, gn_product, neighbour_blocks,
                            normal_blocks)
from .objective import Problem, by_pixel, offset_texels, prior_degree
from ..transfer import to_device

__all__ = ["Stencil", "cell_side", "offsets", "cells_fit", "with_stencil", "stencil_blocks", "stencil_product", "channel_blocks",
           "channel_product", "gauss_newton_operator", "gauss_newton_product", "stencil_covers",
           "data_blocks", "data_neighbour_blocks"]

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


def _tap_steps(index, samples: int, shape: tuple[int, int]):
    """Each pixel's taps (``index`` (R, 4), `samples` rows a pixel, a host array) as grid steps
    from its first tap along rows and along columns, each (P, 4 S) (`_steps`, cells of side
    `cell_side`)."""
    h, w = shape
    side = cell_side(samples)
    index = np.asarray(index, np.int32).reshape(-1, 4 * samples)
    row, col = index // w, index % w
    return _steps(row - row[:, :1], h, side, np), _steps(col - col[:, :1], w, side, np)


def cells_fit(index, samples: int, shape: tuple[int, int]) -> bool:
    """Whether the taps of every pixel (``index`` (R, 4), `samples` rows a pixel, host arrays) lie
    in one cell of side `cell_side` of the ``shape`` map (wrapped), as `stencil_blocks` needs."""
    return _fit(*_tap_steps(index, samples, shape), cell_side(samples))


def _fit(sr, sc, side: int) -> bool:
    return all(not np.any(np.max(st, axis=1) - np.min(st, axis=1) > side - 1) for st in (sr, sc))


class Stencil(eqx.Module):
    """Where a problem's texels and pixels sit on its map (`with_stencil`): each texel's neighbour at
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


def with_stencil(problem: Problem) -> Problem:
    """``problem`` with its `Stencil` (``Problem.stencil``) where it has a ``grid`` and every
    pixel's taps lie in one cell of it (`cells_fit`), else with none: its products then go through
    the pixels. Made on the host from the problem's grid, taps and prior pairs, so a problem whose
    pixels or pairs change gets it again (`pbrfit.fitting.sharding`). A pixel's cell starts at the
    smallest row and column among its taps (wrapped). A texel past H W (a coarser level's
    padding) is its own neighbour at every offset: no pixel reads it, and its blocks are zero.
    The per-pixel tables are placed as the problem's pixels are, the rest as its texels."""
    if problem.grid is None:
        return dataclasses.replace(problem, stencil=None)
    h, w = (int(n) for n in np.asarray(problem.grid.shape))
    samples = problem.samples
    side = cell_side(samples)
    index = np.asarray(problem.index, np.int32)
    sr, sc = _tap_steps(index, samples, (h, w))
    if not _fit(sr, sc, side):
        return dataclasses.replace(problem, stencil=None)
    neighbours = offset_texels((h, w), problem.num_texels, offsets(side))
    p = problem.num_pixels
    first = index.reshape(p, 4 * samples)[:, 0]
    low_r, low_c = np.min(sr, axis=1), np.min(sc, axis=1)
    cell = np.mod(first // w + low_r, h) * w + np.mod(first % w + low_c, w)
    corner = side * (sr - low_r[:, None]) + (sc - low_c[:, None])  # (P, 4 S)
    # each sample's tap weights summed per corner of the cell: one bincount over (pixel, sample, corner)
    slot = (np.arange(p * samples, dtype=np.int64)[:, None] * side * side
            + corner.reshape(p * samples, 4)).reshape(-1)
    weight = np.asarray(problem.weight)
    share = np.bincount(slot, weight.reshape(-1), p * samples * side * side).astype(weight.dtype)
    pairs = np.asarray(problem.pairs, np.int32)
    a, b = pairs[:, 0], pairs[:, 1]
    pi, pj = _steps(b // w - a // w, h, side, np), _steps(b % w - a % w, w, side, np)
    pair_offsets = np.stack([_slot(pi, pj, side), _slot(-pi, -pj, side)], axis=1)

    def place(host, like):
        return jax.device_put(host, like.sharding) if isinstance(like, jax.Array) else to_device(host)

    st = Stencil(place(neighbours, problem.free), place(cell.astype(np.int32), problem.index),
                 place(share.reshape(p, samples, side * side), problem.index),
                 place(pair_offsets.astype(np.int32), problem.pairs))
    return dataclasses.replace(problem, stencil=st)


def _offset_blocks(jac: Float[Array, "R 3 K"], problem: Problem, st: Stencil, pairs) -> Float[Array, "T N K K"]:
    """`_by_offset` of C_c,ab = Σ_(p in cell c) B_paᵀ B_pb, per corner pair (a, b) of ``pairs``
    over every cell c (module docstring): a segment sum over the pixels' cells per pair."""
    t = problem.num_texels
    # by elements (`block_gram`; the flash scene's 2 × 2 samples: 184 ms an assembly against 464)
    if problem.samples == 1:
        # J_pᵀJ_p is symmetric: its upper triangle alone is summed, then mirrored (the same sums,
        # 15 of 25 a pixel for K = 5)
        k = jac.shape[-1]
        upper_i, upper_j = np.triu_indices(k)
        gp = jnp.sum(jac[:, :, upper_i] * jac[:, :, upper_j], axis=1)  # (P, K (K + 1) / 2)
        place = np.zeros((k, k), np.int32)
        place[upper_i, upper_j] = place[upper_j, upper_i] = np.arange(len(upper_i))

        def pair_rows(a, b):  # w_pa w_pb J_pᵀJ_p
            return (st.share[:, 0, a] * st.share[:, 0, b])[:, None] * gp
    else:
        jb = jnp.sum(st.share[:, :, :, None, None] * by_pixel(jac, problem)[:, :, None], axis=1)  # (P, c², 3, K)

        def pair_rows(a, b):  # B_paᵀ B_pb
            return block_gram(jb[:, a], jb[:, b])

    # a scan step per corner pair: the rows of all pairs at once make a buffer (over 32 MiB for
    # 60k pixels) that the allocator maps afresh at each call, and took five times as long
    _, cells = lax.scan(lambda _, ab: (None, jax.ops.segment_sum(pair_rows(ab[0], ab[1]), st.cell, num_segments=t)),
                        None, jnp.asarray(np.asarray(pairs, np.int32)))
    if problem.samples > 1:
        return _by_offset(cells, st, _swap, pairs)
    # every block is symmetric (a sum of w_pa w_pb J_pᵀJ_p): placed by offset as its upper
    # triangle, then mirrored once
    return _by_offset(cells, st, lambda block: block, pairs)[..., place]


def stencil_blocks(jac: Float[Array, "R 3 K"], problem: Problem, st: Stencil) -> Float[Array, "T N K K"]:
    """JᵀJ + smooth L by stencil (module docstring): block n of texel t is the K × K block between
    t and ``st.neighbours[t, n]``, ``st`` the problem's `Stencil`. The prior adds
    smooth w (e_a - e_b)(e_a - e_b)ᵀ ⊗ diag(freed channels) for each pair (a, b) of weight w."""
    t = problem.num_texels
    blocks = _offset_blocks(jac, problem, st, _corner_pairs(st.side))
    a, b = problem.pairs[:, 0], problem.pairs[:, 1]
    sw = problem.smooth * problem.pair_weight
    n = st.neighbours.shape[1]
    at = jnp.concatenate([a * n + st.centre, b * n + st.centre, a * n + st.pair_offsets[:, 0],
                          b * n + st.pair_offsets[:, 1]])
    prior = jax.ops.segment_sum(jnp.concatenate([sw, sw, -sw, -sw]), at, num_segments=t * n).reshape(t, n)
    return blocks + prior[:, :, None, None] * jnp.diag(jnp.max(problem.free, axis=0))


def stencil_covers(problem: Problem, shape: Optional[tuple[int, int]] = None) -> bool:
    """Whether ``problem`` has a stencil whose offsets reach distinct texels of its map (``shape``,
    else its grid's, read from the device): at least 2 side - 1 texels each way. Then its blocks
    at offsets of one step are JᵀJ's blocks between those texels, and its middle one the diagonal
    block, alone."""
    st = problem.stencil
    if st is None:
        return False
    shape = tuple(int(n) for n in np.asarray(problem.grid.shape)) if shape is None else shape
    return min(shape) >= 2 * st.side - 1


def data_blocks(jac: Float[Array, "R 3 K"], problem: Problem, by_stencil: bool) -> Float[Array, "T K K"]:
    """`pbrfit.fitting.normal_matrix.normal_blocks`, JᵀJ's diagonal blocks (pixels only, no
    prior): ``by_stencil`` (static; where `stencil_covers` the problem's map) D_t = Σ_a
    C_(t - o_a),aa, a segment sum over the pixels' cells per corner, else through the pixels (on
    the flash scene's 2 × 2 samples a sort and two segment sums over its 552k sample rows)."""
    if not by_stencil:
        return normal_blocks(jac, problem)
    st = problem.stencil
    pairs = [(a, a) for a in range(st.side * st.side)]
    return _offset_blocks(jac, problem, st, pairs)[:, st.centre]


def data_neighbour_blocks(jac: Float[Array, "R 3 K"], problem: Problem, shape: tuple[int, int]) -> Float[Array, "T 4 K K"]:
    """`pbrfit.fitting.normal_matrix.neighbour_blocks` (JᵀJ's blocks towards the neighbours of
    `NEIGHBOUR_OFFSETS`) of a problem on the ``shape`` map: read from its blocks by stencil where
    `stencil_covers` it (a segment sum per corner pair one step apart, 6 or 20, against a scatter
    per pair of a pixel's taps, 6 or 120), else through the pixels."""
    if not stencil_covers(problem, shape):
        return neighbour_blocks(jac, problem, shape)
    st, side = problem.stencil, problem.stencil.side
    corners = _corners(side)
    steps = {o for di, dj in NEIGHBOUR_OFFSETS for o in ((di, dj), (-di, -dj))}
    pairs = [(a, b) for a, b in _corner_pairs(side)
             if (corners[b][0] - corners[a][0], corners[b][1] - corners[a][1]) in steps]  # (b, a): the reverse
    blocks = _offset_blocks(jac, problem, st, pairs)
    return jnp.stack([blocks[:, _slot(di, dj, side)] for di, dj in NEIGHBOUR_OFFSETS], axis=1)


def _corners(side: int) -> list[tuple[int, int]]:
    """The (i, j) offsets of a cell's corners from its first, numbered row by row."""
    return [(i, j) for i in range(side) for j in range(side)]


def _swap(block):
    """A stack of K × K blocks, each transposed: the block of a pair taken the other way round."""
    return jnp.swapaxes(block, 1, 2)


def _corner_pairs(side: int) -> list[tuple[int, int]]:
    """The cell's corner pairs (a, b), a <= b, corners numbered row by row."""
    return [(a, b) for a in range(side * side) for b in range(a, side * side)]


def _by_offset(cells, st: Stencil, transpose, pairs=None):
    """(T, N, ...) the stencil's blocks from the cells' sums per corner pair, ``cells[q]`` (T, ...)
    for the q-th pair of ``pairs`` (default `_corner_pairs`; blocks no pair reaches are 0): block
    (t, t + o) adds pair (a, b)'s sum over the cell t is corner a of, for o_b - o_a = o, and
    ``transpose`` of it for the pair the other way round."""
    side = st.side
    corners = _corners(side)
    slots = [[] for _ in range(st.neighbours.shape[1])]
    for q, (qa, qb) in enumerate(_corner_pairs(side) if pairs is None else pairs):
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
    """JᵀJ + smooth L at the per-row Jacobians ``jac``, as arrays a solver can keep across steps:
    (its diagonal blocks (T, K, K), its factors for `gauss_newton_product`). The factors are its
    blocks by stencil (T, N, K, K) where ``st`` (the problem's `Stencil`) is given, else
    `pbrfit.fitting.normal_matrix.gauss_newton_factors` (the products go through the pixels)."""
    if st is None:
        eye = jnp.eye(jac.shape[-1], dtype=jac.dtype)
        blocks = normal_blocks(jac, problem) + problem.smooth * prior_degree(problem)[:, None, None] * eye
        return blocks, gauss_newton_factors(jac, problem)
    full = stencil_blocks(jac, problem, st)
    return full[:, st.centre], full


def gauss_newton_product(factors, v: Float[Array, "T K"], problem: Problem, st: Optional[Stencil]):
    """(JᵀJ + smooth L) v from the factors of `gauss_newton_operator`: by stencil where ``st``
    is given, else through the pixels (`pbrfit.fitting.normal_matrix.gn_product`)."""
    if st is None:
        return gn_product(factors, v, problem)
    return stencil_product(factors, st.neighbours, v)
