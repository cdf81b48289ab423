"""Per-texel standard errors from the Gauss-Newton normal matrix at the solution.

Near the optimum of a least-squares problem with independent residual noise of variance σ², the
covariance of the estimate is σ² (JᵀJ)⁻¹ (e.g. Nocedal & Wright, "Numerical Optimization",
2nd ed., section 10.3; Hartley & Zisserman, section 5.2). We keep the per-texel 5 × 5 diagonal
blocks D_t of JᵀJ (`pbrfit.fitting.normal_matrix.normal_blocks`) restricted to the fitted channels, invert
them, and scale by the residual variance σ̂² = 2 E / (residuals - parameters). Inverting a block
alone gives each texel's error with its neighbours held at their values: pixels read four texels
at once (bilinear filtering), so a texel trades off against its neighbours, and the errors come
out optimistic (the conditional variance, not the marginal one).

`window_standard_errors` takes that coupling in: for each texel it builds the normal matrix of
the (2r + 1)² texels around it from the diagonal blocks and the neighbour blocks
(`pbrfit.fitting.normal_matrix.neighbour_blocks`), and inverts it. The texel's block of that inverse is
(D_t - B_t S_t⁻¹ B_tᵀ)⁻¹, with S_t the other texels' matrix and B_t their coupling to t (a Schur
complement): the texel's error with the window's other texels free and the texels beyond it
held. The errors grow with r, from the per-texel blocks' (r = 0) towards the marginal
σ² diag((JᵀJ)⁻¹) of the whole map: for a positive definite A whose principal submatrix W holds
the window, the window's part of A⁻¹ is (W - X)⁻¹ with X ⪰ 0 the Schur term of the texels
outside it, hence ⪰ W⁻¹ (the partitioned inverse; e.g. Horn & Johnson, "Matrix Analysis", on the
Schur complement), and a wider window is a larger principal submatrix. On data_synth's flash
scene at 4 views of 32² and an 8 × 8 map, whose matrix can be inverted whole, r = 0 gives a
median 83% of the marginal σ, r = 1 98% and r = 2 99.9%.
`experiments/uncertainty.py` measures the calibration of each r against the spread of repeated
fits under fresh noise.

A channel that sits on a bound of its range is held by the projected solver
(`pbrfit.fitting.solvers.structured`): `window_standard_errors` then holds it for the other channels' errors as
well (``pinned``). Counted as free, a binary metallic map at 0 and 1 widened base colour's σ
on the flash scene until the fits scattered by 0.62 σ (experiments/uncertainty.md).

σ̂² is one variance for every residual. `sandwich_ratios` compares, per texel and channel, the
variance its own pixels' residuals show (the sandwich D⁻¹ M D⁻¹ of its block) with σ̂² D⁻¹; the
fit widens σ by that ratio where it exceeds 1 (`pbrfit.fitting.result.misfit_ratios`): the texels
whose pixels the model misses.

A direction the images do not constrain (a channel no view separates, e.g. roughness where no
highlight is ever seen) has a tiny eigenvalue: its σ is large, and +inf when the eigenvalue is
below `EIGEN_FLOOR` of the block's largest. Fixed channels get 0, unobserved texels +inf.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .normal_matrix import NEIGHBOUR_OFFSETS

__all__ = ["EIGEN_FLOOR", "MAX_UNCERTAINTY_RADIUS", "WINDOW_RADIUS", "block_standard_errors", "residual_variance",
           "sandwich_ratios", "window_precisions", "window_radii", "window_standard_errors", "WindowCache"]

#: Eigenvalues below this fraction of a block's largest count as unconstrained (float32 round-off
#: of JᵀJ sits near 1e-7 relative; 1e-10 in the float64 inversion keeps only exact degeneracies).
EIGEN_FLOOR = 1e-10
#: The default window radius of `window_standard_errors` (`fit`'s ``uncertainty_radius``).
WINDOW_RADIUS = 1
#: The largest radius `fit` takes: a window of (2 r + 1)² texels costs about ((2 r + 1)² K)³ / 3
#: per texel, host float64 (K = 5 on this 2-core CPU: r = 1 0.12 s and r = 2 about 1 s for a
#: 64² map, 256 times that at 1024²; r = 3 would take hours at 256²).
MAX_UNCERTAINTY_RADIUS = 2
#: Ridge added to the window's Jacobi-scaled matrix (unit diagonal) before it is solved: keeps a
#: direction no pixel constrains (whose coupling is zero as well) from making it singular, at the
#: float32 round-off of the blocks (about 1e-7), below which a direction cannot be told from one
#: the pixels leave free.
WINDOW_RIDGE = 1e-6
#: Bytes of window matrices assembled at once (float64): few enough that the chunks' arrays stay
#: in cache and the allocator reuses their memory from chunk to chunk, many enough that the
#: loop's per-chunk overhead stays small (258 texels a chunk with 3 × 3 windows of 5 channels).
#: On the peer scene, against 64 MiB: the hold's standard errors took 0.11 to 0.13 s of a fit
#: in a script instead of 0.15 to 0.7 s, and the command's peak memory fell from 1,036-1,043 to 909 MiB.
_WINDOW_CHUNK_BYTES = 1 << 22


def _threads() -> int:
    """The threads `_in_chunks` runs on: the cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _in_chunks(work, total: int, chunk: int) -> None:
    """``work(lo, hi)`` over [0, total) in chunks of ``chunk``, on `_threads` threads: numpy's
    gathers and batched linear algebra release the GIL, so the host's cores share the chunks.
    Each chunk's numbers are the same whichever thread computes it (each matrix is its own
    LAPACK call); ``work`` writes its own rows of the output. An error or an interrupt cancels
    the chunks not begun, and is raised without waiting for those under way."""
    chunk = max(1, chunk)
    starts = range(0, total, chunk)
    threads = min(_threads(), len(starts))
    if threads <= 1:
        for lo in starts:
            work(lo, min(lo + chunk, total))
        return
    pool = ThreadPoolExecutor(threads)
    try:
        for done in [pool.submit(work, lo, min(lo + chunk, total)) for lo in starts]:
            done.result()
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def residual_variance(loss: float, residual_count: int, parameter_count: int) -> float:
    """σ̂² = 2 E / (n - p): the unbiased noise estimate of a least-squares fit."""
    dof = max(residual_count - parameter_count, 1)
    return 2.0 * float(loss) / dof


def _fitted_eigh(blocks: np.ndarray, free: np.ndarray, seen: np.ndarray):
    """The eigenpairs of each block restricted to its ``free`` channels (identity on the others;
    float64): (e, V, which eigenvalues are above `EIGEN_FLOOR` of the largest, which blocks are
    broken (non-finite: an overflowed solve's, `pbrfit.fit` refuses it; eigh of the identity
    there), the (T, K, K) mask of the free channels' entries of seen texels)."""
    blocks = np.asarray(blocks, np.float64)
    mask2 = free[:, :, None] & free[:, None, :] & seen[:, None, None]  # (nothing of an unseen texel is read)
    eye = np.eye(blocks.shape[1])
    b = np.where(mask2, blocks, 0.0) + np.where(free, 0.0, 1.0)[:, :, None] * eye
    broken = ~np.all(np.isfinite(b), axis=(1, 2))
    b = np.where(broken[:, None, None], eye, b)
    e, v = np.empty(b.shape[:2]), np.empty(b.shape)

    def eigenpairs(lo, hi):
        e[lo:hi], v[lo:hi] = np.linalg.eigh(b[lo:hi])

    _in_chunks(eigenpairs, len(b), -(-len(b) // _threads()))
    top = np.max(np.abs(e), axis=1, keepdims=True)
    ok = e > EIGEN_FLOOR * np.maximum(top, np.finfo(np.float64).tiny)
    return e, v, ok, broken, mask2


def block_standard_errors(blocks: np.ndarray, channels: np.ndarray, seen: np.ndarray, sigma2: float) -> np.ndarray:
    """(T, K) one-sigma errors from (T, K, K) normal-matrix blocks, the (K,) fitted-channel mask
    and the (T,) observed-texel mask (K = 5, or 7 with normals).

    σ_c² = σ̂² Σ_k V_ck² / e_k over the eigenpairs (e_k, V_k) of the block restricted to the
    fitted channels; 0 for fixed channels; +inf for fitted channels of texels no pixel reads.
    """
    free = np.broadcast_to(np.asarray(channels, bool), np.asarray(blocks).shape[:2])
    seen = np.asarray(seen, bool)
    return _errors(*_variance_factors(blocks, free, seen), free, seen, sigma2)


def _variance_factors(blocks: np.ndarray, free: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`block_standard_errors` before σ̂²: (T, K) Σ_k V_ck² / e_k of each block restricted to its
    free channels (+inf along a degenerate direction), and (T,) which blocks are broken; each
    row a function of its own block, free channels and seen flag alone."""
    e, v, ok, broken, _ = _fitted_eigh(blocks, free, seen)
    inv_e = np.where(ok, 1.0 / np.where(ok, e, 1.0), np.inf)
    # Σ_k V_ck² / e_k, with 0 · inf taken as 0 (a degenerate direction that misses channel c).
    with np.errstate(invalid="ignore"):
        contrib = np.where(v * v > 0, v * v * inv_e[:, None, :], 0.0)
        return np.sum(contrib, axis=2), broken


def _errors(total, broken, free, seen, sigma2) -> np.ndarray:
    """`block_standard_errors` from its `_variance_factors`."""
    with np.errstate(invalid="ignore"):  # (a NaN σ̂² from an overflowed solve: `pbrfit.fit` refuses it)
        # a direction no pixel constrains is unknown even where the fit is exact (σ̂² = 0): +inf, not 0 · inf
        out = np.where(np.isposinf(total), np.inf, np.sqrt(sigma2 * np.where(np.isposinf(total), 0.0, total)))
    out = np.where(seen[:, None], np.where(broken[:, None], np.nan, out), np.inf)
    return np.where(free, out, 0.0).astype(np.float32)


def sandwich_ratios(blocks: np.ndarray, meat: np.ndarray, channels: np.ndarray, seen: np.ndarray, sigma2: float,
                    dof_scale: float = 1.0, pinned: np.ndarray | None = None) -> np.ndarray:
    """(T, K) per texel and channel, the variance the residuals show over the one the noise model
    gives: ρ_c = [D⁻¹ M D⁻¹]_cc / (σ̂² [D⁻¹]_cc), D the texel's normal-matrix block and
    M = Σ_p B_ptᵀ r_p r_pᵀ B_pt its "meat" (B_pt the pixel's Jacobian in the texel's channels,
    r_p its residuals: `pbrfit.fitting.normal_matrix.normal_blocks` of the rows' r_pᵀ J_p), times
    ``dof_scale`` (n / (n - p), as σ̂² divides by n - p).

    D⁻¹ M D⁻¹ is the heteroskedasticity-consistent ("sandwich") covariance of the texel's
    estimate (H. White, "A heteroskedasticity-consistent covariance matrix estimator and a direct
    test for heteroskedasticity", Econometrica 48, 1980; with the n / (n - p) scale, MacKinnon
    & White 1985's HC1): it reads the variance from the residuals of the pixels that inform each
    channel, where σ̂² D⁻¹ assumes every residual has the same variance σ̂². Under that model
    E[M] = σ² D and ρ ≈ 1; where the model misses light that the texel's most informative pixels
    carry (a highlight it cannot match, a wrong basin), ρ > 1. Channels on a degenerate
    direction (σ = inf) and unseen texels get 1; ``pinned`` channels, held by the solver, are
    held for the others' ratios (as `window_standard_errors` holds them), and their own ratio
    is that with every channel free."""
    free = np.broadcast_to(np.asarray(channels, bool), np.asarray(blocks).shape[:2])
    if pinned is not None and np.any(pinned & free):
        everyone = sandwich_ratios(blocks, meat, free, seen, sigma2, dof_scale)
        held = sandwich_ratios(blocks, meat, free & ~pinned, seen, sigma2, dof_scale)
        return np.where(pinned & free, everyone, held)
    seen = np.asarray(seen, bool)
    e, v, ok, broken, mask2 = _fitted_eigh(blocks, free, seen)
    meat = np.asarray(meat, np.float64) * dof_scale
    broken = broken | ~np.all(np.isfinite(meat), axis=(1, 2))
    inv_e = np.where(ok, 1.0 / np.where(ok, e, 1.0), 0.0)
    d_inv = np.einsum("tij,tj,tkj->tik", v, inv_e, v)
    m = np.where(mask2 & ~broken[:, None, None], meat, 0.0)
    robust = np.einsum("tci,tij,tcj->tc", d_inv, m, d_inv)
    classic = sigma2 * np.diagonal(d_inv, axis1=1, axis2=2)
    # a channel on a degenerate direction has σ = inf whatever the ratio
    degenerate = np.any((v * v > 0) & ~ok[:, None, :], axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(classic > 0, robust / np.where(classic > 0, classic, 1.0), 1.0)
    use = free & seen[:, None] & ~degenerate & ~broken[:, None] & np.isfinite(ratio)
    return np.where(use, ratio, 1.0)


def window_radii(shape: tuple[int, int], radius: int) -> tuple[int, int]:
    """The window's half sizes (r_i, r_j) on an (H, W) map: at most `radius`, and small enough
    that the window's texels are distinct and that none of them is a neighbour of another through
    the map's wrap unless it is one inside the window (2 r + 2 <= H)."""
    h, w = shape
    return max(0, min(radius, (h - 2) // 2)), max(0, min(radius, (w - 2) // 2))


def window_precisions(blocks: np.ndarray, couplings: np.ndarray, shape: tuple[int, int], channels: np.ndarray,
                      seen: np.ndarray, radius: int, texels: np.ndarray | None = None) -> np.ndarray:
    """(T, K, K) precision of each texel's channels with the other texels of its window free:
    P_t = D_t - B_t S_t⁻¹ B_tᵀ (float64), from the diagonal blocks D (T, K, K), the neighbour
    blocks C (T, 4, K, K) of `pbrfit.fitting.normal_matrix.neighbour_blocks`, the (K,) or (T, K) fitted-channel mask and
    the (T,) observed-texel mask. Fixed channels and unobserved texels take no part (their rows
    are replaced by the identity; a channel no texel fits is left out of the matrices). S is
    Jacobi-scaled and gets a `WINDOW_RIDGE` before the solve. (On the peer scene's 4096 texels,
    metallic uniform: 83 ms, of which the solves 36.) ``texels``: the indices of the texels
    whose precisions to compute, (len(texels), K, K), each the same numbers as among all of them."""
    h, w = shape
    t, k = blocks.shape[0], blocks.shape[1]
    wanted = np.arange(t) if texels is None else np.asarray(texels, np.intp)
    free = np.asarray(channels, bool)
    seen = np.asarray(seen, bool)
    taking_part = np.any(seen[:, None] & np.broadcast_to(free, (t, k)), axis=0)
    if not taking_part.all():  # the window matrices of the channels some texel fits (their rows alone)
        out = np.zeros((len(wanted), k, k))
        c = np.flatnonzero(taking_part)
        if c.size:
            out[:, c[:, None], c[None, :]] = window_precisions(blocks[:, c][:, :, c], couplings[:, :, c][:, :, :, c],
                                                               shape, free[..., c], seen, radius, wanted)
        return out
    ri, rj = window_radii(shape, radius)
    # the texel itself first, so that its channels are the window matrix's first K rows
    offsets = [(0, 0)] + [(di, dj) for di in range(-ri, ri + 1) for dj in range(-rj, rj + 1) if (di, dj) != (0, 0)]
    n = len(offsets)
    if n == 1:
        return np.asarray(blocks, np.float64)[wanted]

    codes = {o: q for q, o in enumerate(NEIGHBOUR_OFFSETS)}
    # each (a, b) block of a window's matrix: D of texel a, C of texel a towards b, or C of b
    # towards a transposed (blocks further apart are zero)
    diag_ab, ahead, behind = [], [], []  # (a, b), and (a, b, code) for the other two
    for a, (ai, aj) in enumerate(offsets):
        for b, (bi, bj) in enumerate(offsets):
            rel = (bi - ai, bj - aj)
            if rel == (0, 0):
                diag_ab.append((a, b))
            elif rel in codes:
                ahead.append((a, b, codes[rel]))
            elif (-rel[0], -rel[1]) in codes:
                behind.append((a, b, codes[(-rel[0], -rel[1])]))
    diag_ab, ahead, behind = (np.array(v, np.intp) for v in (diag_ab, ahead, behind))
    q = len(NEIGHBOUR_OFFSETS)
    rows, cols = np.divmod(np.arange(t), w)

    def texels(at, steps):  # (len(at), len(steps)): the texels the steps lead to, wrapped
        return np.stack([((rows[at] + di) % h) * w + (cols[at] + dj) % w for di, dj in steps], axis=1)

    # rows and columns that take no part are zeroed here, so that nothing in them (a non-finite
    # derivative of a fixed channel) reaches the window's solve
    part = seen[:, None] & np.broadcast_to(free, (t, k))  # (T, K)
    towards = texels(slice(None), NEIGHBOUR_OFFSETS)
    blocks = np.where(part[:, :, None] & part[:, None, :], blocks, 0.0)
    flat = np.where(part[:, None, :, None] & part[towards][:, :, None, :], couplings, 0.0).reshape(t * q, k, k)
    # every block a window matrix can hold: D, C, Cᵀ and a zero block (the last); each chunk's
    # windows in float64
    source = np.concatenate([blocks, flat, np.swapaxes(flat, 1, 2), np.zeros((1, k, k), blocks.dtype)])
    out = np.empty((len(wanted), k, k))
    rest = np.arange(k, n * k)

    def windows(lo, hi):
        ts = wanted[lo:hi]
        u = texels(ts, offsets)  # (c, n)
        # the (a, b) block of each window: its place in `source`, then one gather
        at = np.full((len(ts), n, n), len(source) - 1)
        at[:, diag_ab[:, 0], diag_ab[:, 1]] = u[:, diag_ab[:, 0]]
        at[:, ahead[:, 0], ahead[:, 1]] = t + u[:, ahead[:, 0]] * q + ahead[:, 2]
        at[:, behind[:, 0], behind[:, 1]] = t + t * q + u[:, behind[:, 1]] * q + behind[:, 2]
        # (c, n, K, n, K) as (c, n K, n K)
        m = np.swapaxes(source[at], 2, 3).astype(np.float64, order="C").reshape(len(ts), n * k, n * k)
        on = part[u].reshape(len(ts), n * k)
        diag = np.diagonal(m, axis1=1, axis2=2)
        live = on & (diag > 0)  # a row of JᵀJ with a zero diagonal is zero (positive semi-definite)
        # Jacobi scaling, 0 for the rows that take no part (the identity's, below)
        scale = np.where(live, 1.0 / np.sqrt(np.where(live, diag, 1.0)), 0.0)
        m *= scale[:, :, None]
        m *= scale[:, None, :]
        m[:, np.arange(k), np.arange(k)] = 1.0  # the unit diagonal
        m[:, rest, rest] = 1.0 + WINDOW_RIDGE  # and S's, with the ridge
        b = m[:, :k, k:]
        p = m[:, :k, :k] - b @ np.linalg.solve(m[:, k:, k:], np.swapaxes(b, 1, 2))
        p = 0.5 * (p + np.swapaxes(p, 1, 2))
        keep = live[:, :k]
        own = np.where(keep, scale[:, :k], 1.0)
        out[lo:hi] = np.where(keep[:, :, None] & keep[:, None, :], p / own[:, :, None] / own[:, None, :], 0.0)

    _in_chunks(windows, len(wanted), _WINDOW_CHUNK_BYTES // (8 * n * n * k * k))
    return out


def window_standard_errors(blocks: np.ndarray, couplings: np.ndarray, shape: tuple[int, int], channels: np.ndarray,
                           seen: np.ndarray, sigma2: float, radius: int = WINDOW_RADIUS,
                           pinned: np.ndarray | None = None, cache: "WindowCache | None" = None) -> np.ndarray:
    """(T, K) one-sigma errors with each texel's (2 r + 1)² window free (`window_precisions`),
    as `block_standard_errors` reads a block; never below the per-texel blocks' own (which
    they bound from below in exact arithmetic: where the neighbour blocks leave out couplings
    between texels further apart, the window's matrix is not exactly JᵀJ's). ``radius`` 0 gives
    `block_standard_errors`. ``channels`` is (K,) or per texel (T, K).

    ``pinned`` (T, K), optional: fitted channels that sit on a bound of their range, where a
    projected solver holds them (metallic at 0 or 1, a base colour at 1). The other channels'
    errors are then those with the pinned ones held, as the solver's estimate is; a pinned
    channel's own error stays that with every channel free (its estimate is one-sided).

    ``cache``: a `WindowCache` that keeps the window precisions from one call to the next, so
    that a call whose blocks and masks changed at a few texels computes the windows those reach
    alone (the same numbers)."""
    free = np.broadcast_to(np.asarray(channels, bool), np.asarray(blocks).shape[:2])
    if pinned is not None and np.any(pinned & free):
        everyone = _window_errors(blocks, couplings, shape, free, seen, sigma2, radius, cache, "free")
        held = _window_errors(blocks, couplings, shape, free & ~pinned, seen, sigma2, radius, cache, "held")
        return np.where(pinned & free, everyone, held)
    return _window_errors(blocks, couplings, shape, free, seen, sigma2, radius, cache, "free")


def _window_errors(blocks, couplings, shape, free, seen, sigma2, radius, cache, key):
    """`window_standard_errors` of the (T, K) ``free`` channels, from ``cache``'s precisions and
    factors under ``key`` where it is given."""
    seen = np.asarray(seen, bool)

    def errors(part, matrices):
        factors = (_variance_factors(matrices, free, seen) if cache is None
                   else cache.factors((part, key), matrices, free, seen))
        return _errors(*factors, free, seen, sigma2)

    own = errors("own", blocks)
    if radius <= 0:
        return own
    if cache is None:
        precisions = window_precisions(blocks, couplings, shape, free, seen, radius)
    else:
        precisions = cache.precisions(key, blocks, couplings, shape, free, seen, radius)
    return np.maximum(errors("window", precisions), own)


class WindowCache:
    """The window precisions of `window_standard_errors`' last call (one set per choice of the
    channels held: all free, or those on a bound held) with the blocks and masks they came
    from. A later call recomputes the windows that hold a texel whose diagonal block, neighbour
    blocks or channels changed, and keeps the others' precisions, which are the same numbers:
    the hold of unconstrained roughness (`pbrfit.fitting.stages.unconstrained`) takes the
    standard errors again after re-fitting a few texels, where every other window is as it was
    (experiments/speed.md). It keeps the blocks and couplings it is given, not copies: a caller
    passes new arrays to a later call, not the same ones changed in place."""

    def __init__(self):
        self._last: dict = {}

    def precisions(self, key, blocks, couplings, shape, free, seen, radius) -> np.ndarray:
        """`window_precisions` of these arguments, from the last call under ``key`` where it can."""
        blocks, couplings = np.asarray(blocks), np.asarray(couplings)
        # (a window reads the texels seen through these alone; which channels take part at all
        # shapes every window)
        part = np.asarray(seen, bool)[:, None] & np.broadcast_to(np.asarray(free, bool), blocks.shape[:2])
        t, (h, w) = blocks.shape[0], shape
        last = self._last.get(key)
        same_frame = (last is not None and t == h * w and last["shape"] == tuple(shape) and last["radius"] == radius
                      and last["blocks"].shape == blocks.shape
                      and np.array_equal(np.any(last["part"], axis=0), np.any(part, axis=0)))
        if not same_frame:
            out = window_precisions(blocks, couplings, shape, free, seen, radius)
        else:
            changed = (_rows_differ(blocks, last["blocks"]) | _rows_differ(couplings, last["couplings"])
                       | _rows_differ(part, last["part"]))
            redo = np.flatnonzero(_windows_holding(changed, shape, radius))
            out = last["out"].copy()
            if redo.size:
                out[redo] = window_precisions(blocks, couplings, shape, free, seen, radius, redo)
        self._last[key] = dict(shape=tuple(shape), radius=radius, blocks=blocks, couplings=couplings, part=part,
                               out=out)
        return out

    def factors(self, key, matrices, free, seen) -> tuple[np.ndarray, np.ndarray]:
        """`_variance_factors` of these arguments, its rows from the last call under ``key`` where
        the row's matrix, free channels and seen flag are as they were."""
        last = self._last.get(key)
        if last is None or last["matrices"].shape != matrices.shape:
            total, broken = _variance_factors(matrices, free, seen)
        else:
            changed = np.flatnonzero(_rows_differ(matrices, last["matrices"]) | _rows_differ(free, last["free"])
                                     | (seen != last["seen"]))
            total, broken = last["total"].copy(), last["broken"].copy()
            if changed.size:
                total[changed], broken[changed] = _variance_factors(matrices[changed], free[changed], seen[changed])
        self._last[key] = dict(matrices=matrices, free=np.array(free), seen=np.array(seen), total=total, broken=broken)
        return total, broken


def _rows_differ(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T,) whether row t of ``a`` differs from row t of ``b`` anywhere (a NaN always does)."""
    return np.any(a != b, axis=tuple(range(1, a.ndim)))


def _windows_holding(texels: np.ndarray, shape: tuple[int, int], radius: int) -> np.ndarray:
    """(H W,) the texels whose window (`window_radii`, wrapped around the map) holds one of ``texels``."""
    h, w = shape
    ri, rj = window_radii(shape, radius)
    grid = np.asarray(texels, bool).reshape(h, w)
    out = np.zeros_like(grid)
    for di in range(-ri, ri + 1):
        for dj in range(-rj, rj + 1):
            out |= np.roll(grid, (di, dj), axis=(0, 1))
    return out.reshape(-1)
