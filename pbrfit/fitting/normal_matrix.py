"""The Gauss-Newton matrix of the objective (`pbrfit.fitting.objective`), matrix-free and by blocks.

The full Jacobian is J_p w_pk in the columns of texel t_pk: the Gauss-Newton matrix
JᵀJ = Σ_p Σ_kl w_pk w_pl [t_pk, t_pl] ⊗ J_pᵀJ_p is block-sparse (K × K blocks between texels that
share a pixel), its diagonal blocks D_t = Σ w_pk² J_pᵀJ_p and the gradient g_t = Σ w_pk J_pᵀ r_p
are segment sums, and a product JᵀJ v costs one gather, a K × K product per pixel and one
scatter-add (`gn_product`). With S samples the Jacobian of pixel p is J_ps = ∂r_p/∂m_ps (3 × K)
per sample; the products go through the pixel's residual space (JᵀJ v = Σ_s J_psᵀ Σ_s' J_ps'
m_ps'(v)), and the diagonal blocks sum, per pixel, the Jacobians of all its taps that read the
same texel before squaring (`normal_blocks`), so they stay exact where samples share texels.
`neighbour_blocks` gives the blocks between neighbouring texels (`pbrfit.fitting.uncertainty`).
`pbrfit.fitting.stencil` holds the whole matrix by blocks, for products that do not go through
the pixels.

Precision: every contraction here passes ``precision=HIGHEST``; JAX's default lets a GPU
multiply float32 in TF32 (10-bit mantissa), too coarse for the normal equations.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from .objective import Problem, by_pixel, laplacian, sample_texels, scatter_texels, to_rows

__all__ = ["normal_blocks", "neighbour_blocks", "NEIGHBOUR_OFFSETS", "gradient", "gauss_newton_factors", "gn_product",
           "spd_block_inverse", "block_gram"]


def block_gram(a: Float[Array, "N C K"], b: Float[Array, "N C L"]) -> Float[Array, "N K L"]:
    """(a_nᵀ b_n)_n: products and sums of elements, not a batched dot, which a CPU runs two to
    three times slower on blocks this small (and a GPU would multiply in TF32)."""
    return jnp.sum(a[:, :, :, None] * b[:, :, None, :], axis=1)


def normal_blocks(jac: Float[Array, "R 3 K"], problem: Problem) -> Float[Array, "T K K"]:
    """Diagonal K × K blocks of JᵀJ (pixels only, no prior): D_t = Σ w_pk² J_pᵀ J_p.

    With S samples per pixel, a pixel's 4 S taps (sample s, bilinear tap k) have Jacobians
    A_j = w_j J_ps; taps that read the same texel add up before squaring:
    D_t = Σ_p B_ptᵀ B_pt with B_pt = Σ_(j: t_j = t) A_j, one segment sum over the pixel's distinct
    texels (memory linear in the taps)."""
    if problem.samples == 1:
        gp = block_gram(jac, jac)
        w2 = problem.weight * problem.weight
        return scatter_texels(w2[:, :, None, None] * gp[:, None], problem)
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
    bb = block_gram(b, b)
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
    the same texel, and the pairs across are left out (`pbrfit.fitting.uncertainty.window_radii` gives
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
    jac = by_pixel(jac, problem)  # (P, S, 3, K)
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
        g = block_gram(ja, jb)
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
    jr = jnp.sum(jac * to_rows(r, problem)[:, :, None], axis=1)
    return scatter_texels(problem.weight[:, :, None] * jr[:, None, :], problem) + problem.smooth * laplacian(x, problem)


def gauss_newton_factors(jac: Float[Array, "R 3 K"], problem: Problem):
    """What `gn_product` needs of the Jacobians: the per-pixel J_pᵀJ_p (P, K, K) with one
    sample per pixel, else the per-sample Jacobians themselves."""
    if problem.samples == 1:
        return block_gram(jac, jac)
    return jac


def gn_product(gp, v, problem: Problem):
    """(JᵀJ + smooth L) v from `gauss_newton_factors` (matrix-free)."""
    mv = sample_texels(v, problem)
    if problem.samples == 1:
        y = jnp.sum(gp * mv[:, None, :], axis=2)
    else:  # J v in the pixels' residual space, then back through each sample's Jacobian
        jac = by_pixel(gp, problem)
        jv = jnp.sum(jac * by_pixel(mv, problem)[:, :, None, :], axis=(1, 3))
        y = jnp.sum(jac * jv[:, None, :, None], axis=2).reshape(mv.shape)
    return scatter_texels(problem.weight[:, :, None] * y[:, None, :], problem) + problem.smooth * laplacian(v, problem)


def spd_block_inverse(m: Float[Array, "T K K"]) -> Float[Array, "T K K"]:
    """The inverses of symmetric positive definite K × K blocks (the block-Jacobi
    preconditioners), by Gauss-Jordan elimination without pivoting on [S | I] → [I | S⁻¹], K
    steps of elementwise arithmetic over all T blocks at once, where S = D^-½ M D^-½ is M
    scaled to a unit diagonal (D = diag M) and M⁻¹ = D^-½ S⁻¹ D^-½.

    Without pivoting each pivot is a Schur complement of S, positive for SPD S, so elimination
    never divides by zero (G. H. Golub and C. F. Van Loan, Matrix Computations, 4th ed., §4.2);
    the scaling takes out the channels' different units (colour against roughness), which
    otherwise cost float32 digits. Plain XLA operations, not LAPACK: ``jnp.linalg.inv`` calls a
    LAPACK kernel that spreads a batch over the CPU's thread pool and waits for it, and with the
    pixels sharded over several CPU devices every device's kernel waited on the pool the others
    held (a fit over 4 forced host devices hung at the solver's first step)."""
    k = m.shape[-1]
    scale = lax.rsqrt(jnp.diagonal(m, axis1=-2, axis2=-1))
    s = m * scale[..., :, None] * scale[..., None, :]
    a = jnp.concatenate([s, jnp.broadcast_to(jnp.eye(k, dtype=m.dtype), m.shape)], axis=-1)
    for i in range(k):
        row = a[..., i, :] / a[..., i, i, None]
        a = a - a[..., :, i, None] * row[..., None, :]
        a = a.at[..., i, :].set(row)
    return a[..., k:] * scale[..., :, None] * scale[..., None, :]
