"""The fit's structured Levenberg-Marquardt solver (`structured_lm`).

On the objective of `pbrfit.fitting.objective`, with the Gauss-Newton matrix of `pbrfit.fitting.normal_matrix`,
the damped normal equations

    (JᵀJ + λ diag(D) + smooth L) δ = -g

are solved by conjugate gradients preconditioned with the inverted diagonal blocks (block
Jacobi), in the span of the *active* channels: free, observed, and not on a bound that the
gradient pushes against. The step is clipped into the box (`pbrfit.fitting.parameters`), accepted if it
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
`pbrfit.fitting.solvers.optx`.

Precision: every contraction here passes ``precision=HIGHEST``; JAX's default lets a GPU
multiply float32 in TF32 (10-bit mantissa), too coarse for the normal equations.
"""

from __future__ import annotations

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float

from ..normal_matrix import gauss_newton_factors, gn_product, gradient, normal_blocks
from ..objective import Problem, linearize, prior_degree
from ..parameters import lower, upper

__all__ = ["structured_lm", "pcg", "LMStats", "CG_RTOL", "DAMPING_FLOOR", "LAMBDA_INIT", "LAMBDA_MAX"]

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
    degree = prior_degree(problem)
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
