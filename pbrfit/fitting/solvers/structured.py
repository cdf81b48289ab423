"""The fit's structured Levenberg-Marquardt solver, `StructuredLM`: an optimistix least-squares
solver whose step is pbrfit's own (the projected, block-Jacobi-preconditioned one).

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

The products: where the problem says so (``Problem.stencil``: each pixel's taps in one cell of
the map, always at pixel centres; `pbrfit.fitting.stencil`), JᵀJ + smooth L is assembled
by stencil once per iterate (`pbrfit.fitting.stencil.stencil_blocks`, its diagonal blocks the
preconditioner's), each step masks and damps the blocks, and each CG iteration is a gather of every
texel's neighbours and their K × K products, whatever the number of pixels (on the peer scene at
64 × 64, 60k pixels: an iteration 0.5 ms against 3.2 ms through the pixels, a step about 30 ms
against 90 on a 2-core CPU, where the linearisation and the assembly now take 9 ms each).
Without one, each product goes through the pixels (`pbrfit.fitting.normal_matrix.gn_product`: a
gather, a K × K product and a scatter per pixel row). Either way JᵀJ and the gradient are made
once per iterate, by the first step from it (`_StructuredLMState.stale`): a rejected step keeps
them, and the next one only damps them more (on the flash scene's 2 × 2 samples an assembly costs
about 0.2 s, as much as the linearisation, and a quarter of the steps are rejected).

Why its own step: optimistix's LM and Gauss-Newton take a lineax solver for the step, but they
do not support bounds (the active set and the projection live between the linear solve and the
acceptance test), and lineax's CG has no preconditioner hook for the block diagonal assembled from
the same per-pixel Jacobians. So `StructuredLM` is an `optx.AbstractLeastSquaresSolver` whose
`step` linearises the problem itself (`pbrfit.fitting.objective.linearize`: residuals and per-pixel
Jacobians in one pass) rather than asking optimistix for a Jacobian: it is run as
``optx.least_squares(fn, StructuredLM(), x0, args=problem, options=dict(max_steps=n))`` with
``args`` the `pbrfit.fitting.objective.Problem` and ``fn(x, problem)`` its residuals
(`pbrfit.fitting.objective.residuals`, what the solve minimises ½ Σ r² of; `solve` does this). The
loop is optimistix's `lax.while_loop`: no host round-trips (the loss at each step is kept in the
state, `HISTORY` of them, and reported after the solve, so the compiled program holds no host
callback and JAX's persistent cache can keep it), every array has a fixed shape, and pixels and
texels can be sharded. The generic optimistix solvers run the same objective through
`pbrfit.fitting.solvers.optx`.

Precision: the blocks' products are sums of elementwise products, not dots
(`pbrfit.fitting.normal_matrix.block_gram`): JAX's default lets a GPU multiply float32 dots in
TF32 (10-bit mantissa), too coarse for the normal equations, and a CPU runs batched dots of
such small blocks two to three times slower.
"""

from __future__ import annotations

from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax import lax
from jaxtyping import Array, Float

from ..defaults import ATOL, CG_RTOL, NOISE_RTOL, RTOL
from ..normal_matrix import gradient, spd_block_inverse
from ..stencil import gauss_newton_operator, gauss_newton_product, stencil_product
from ..objective import Problem, linearize, residuals, rounding_floor
from ..parameters import lower, upper

__all__ = ["StructuredLM", "solve", "pcg", "LMStats", "LMCarry", "RTOL", "ATOL", "NOISE_RTOL", "CG_RTOL",
           "CG_MAX_STEPS", "DAMPING_FLOOR", "LAMBDA_INIT", "LAMBDA_MAX", "HISTORY"]

#: Relative floor on the damping diagonal, times the mean diagonal of the free channels: keeps the
#: damped blocks invertible for channels the images barely constrain (roughness without highlights).
DAMPING_FLOOR = 1e-6
#: Initial Levenberg-Marquardt damping (relative to the diagonal, Marquardt scaling).
LAMBDA_INIT = 1e-3
#: Damping above this means the model cannot be decreased further from here: stop.
LAMBDA_MAX = 1e10
#: Conjugate-gradient iterations per step, at most.
CG_MAX_STEPS = 100
#: Losses a solve keeps, one per call to `step` (the start's first); later steps run unrecorded.
HISTORY = 512
#: The step budget when the options give none: optimistix's ``max_steps`` bounds the solve then.
_NO_BUDGET = jnp.iinfo(jnp.int32).max


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
    """What a `StructuredLM` solve did: steps taken (the linearisation at the start not counted),
    steps accepted, conjugate-gradient iterations, the final E, the final damping λ, and E after
    each call to `step` (``history[0]`` the start's; `HISTORY` of them, NaN past the last); and
    what goes on to a later run of the same solve (`LMCarry.after`): Nielsen's factor ν, the calls
    to `step` and whether a stopping test ended it (not the step budget)."""

    steps: Array
    accepted: Array
    cg_iterations: Array
    loss: Array
    damping: Array
    history: Array
    nu: Array
    calls: Array
    stopped: Array


class LMCarry(eqx.Module):
    """What one run of a solve hands the next (`solve`'s ``carry``), so that a solve run in parts,
    each to a step budget of its own, takes the very steps of one run to the last budget: the
    damping λ, Nielsen's factor ν, the calls to `step` k, the steps accepted, the CG iterations and
    E after each step. The residuals and Jacobians are not carried: the next run's first call to
    `step` linearises at its start again (the same function of the same x), and takes no step."""

    lam: Array
    nu: Array
    k: Array
    accepted: Array
    cg: Array
    history: Array

    @staticmethod
    def start(dtype=jnp.float32) -> "LMCarry":
        """A solve's start (what `StructuredLM.init` makes without a carry)."""
        zero = jnp.asarray(0, jnp.int32)
        return LMCarry(lam=jnp.asarray(LAMBDA_INIT, dtype), nu=jnp.asarray(2.0, dtype), k=zero, accepted=zero, cg=zero,
                       history=jnp.full((HISTORY,), jnp.nan, dtype))

    @staticmethod
    def after(stats: LMStats) -> "LMCarry":
        """Where a solve that returned ``stats`` stands."""
        return LMCarry(lam=stats.damping, nu=stats.nu, k=stats.calls, accepted=stats.accepted,
                       cg=stats.cg_iterations, history=stats.history)


def _active(x, g, free):
    lo = jnp.asarray(lower(x.shape[-1]), x.dtype)
    hi = jnp.asarray(upper(x.shape[-1]), x.dtype)
    blocked = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
    return free * (~blocked).astype(x.dtype)


def _stencil_rows(problem: Problem, st, a):
    """The texels the stencil's conjugate gradients run over: (rows (M,), their neighbours among
    them (M, N), the active channels of the texels the neighbours index). Every texel (M = T)
    where ``problem.texels`` is None, else those texels (indices, padded with T: rows that gather
    zeros, `_rows`, and are their own neighbour), each neighbour left out pointing at a zero row M."""
    if problem.texels is None:
        return slice(None), st.neighbours, a
    t, m = a.shape[0], problem.texels.shape[0]
    rows, own = problem.texels, jnp.arange(m, dtype=jnp.int32)
    slot = jnp.full((t,), m, jnp.int32).at[rows].set(own, mode="drop")
    nb = slot[_rows(st.neighbours, rows)].at[:, st.centre].set(own)
    return rows, nb, jnp.concatenate([_rows(a, rows), jnp.zeros_like(a[:1])])


def _rows(a, rows):
    """``a``'s rows ``rows`` (all where a slice), zeros for the indices past its end."""
    return a[rows] if isinstance(rows, slice) else a.at[rows].get(mode="fill", fill_value=0)


def _with_zero_row(v, rows):
    """``v`` over the conjugate gradients' rows, with the zero row that the texels left out read
    (none where they run over every texel)."""
    return v if isinstance(rows, slice) else jnp.concatenate([v, jnp.zeros_like(v[:1])])


class _StructuredLMState(eqx.Module):
    """The iterate's residuals r (P, 3), per-row Jacobians (R, 3, K) and E; its gradient g, the
    diagonal blocks of JᵀJ + smooth L and that matrix's factors (`gauss_newton_operator`), made
    by the first step from the iterate and kept over rejected steps, and whether they are stale
    (the iterate moved since); the damping λ and Nielsen's factor ν, the count k of calls to
    `step` (step 0 only linearises), whether the last step ended the solve, the steps accepted,
    the CG iterations, the step budget, E after each step (`HISTORY`), and whether the next call
    to `step` only linearises (the first of a run)."""

    r: Array
    jac: Array
    loss: Array
    g: Array
    blocks: Array
    factors: Any
    stale: Array
    lam: Array
    nu: Array
    k: Array
    done: Array
    accepted: Array
    cg: Array
    budget: Array
    history: Array
    fresh: Array


class StructuredLM(optx.AbstractLeastSquaresSolver):
    """Projected Levenberg-Marquardt on the structured objective (module docstring), as an
    optimistix least-squares solver: ``args`` is the `pbrfit.fitting.objective.Problem`, and ``fn``
    (its residuals, `pbrfit.fitting.objective.residuals`) is not called, as `step` linearises the
    problem itself.

    Stops at an accepted step that lowers E by less than ``rtol · E``, at a step, accepted or
    not, whose predicted and actual changes of E are both within ``rtol · E`` (MINPACK's ftol
    test: J. J. Moré, B. S. Garbow, K. E. Hillstrom, "User guide for MINPACK-1", ANL-80-74, 1980)
    or that moves no value by more than `atol` (in `norm`, the max norm by default), at an
    accepted step whose predicted and actual decreases of E are both within
    ``noise_rtol · E · p / (n - p)`` (p free channels, n pixel residuals: ``noise_rtol`` times
    p σ̂² / 2, σ̂² the residuals' variance; `pbrfit.fitting.defaults.NOISE_RTOL` says why), once E is
    within the targets' float32 rounding (`pbrfit.fitting.objective.rounding_floor`: there E's
    changes are rounding, larger than ``rtol · E``, and the tests above wait for λ), when λ
    passes `LAMBDA_MAX`, or after ``options["max_steps"]`` steps (an int32 array, so that one compiled
    program serves every budget; without it, optimistix's ``max_steps`` bounds the solve, and
    counts the first call to `step`, which only linearises at the start clipped into the box).
    The final state holds the residuals ``r`` and Jacobians ``jac`` at the returned x, and
    `postprocess` the stats of `LMStats`, E at each step among them (`solve` gathers both).

    ``cg_rtol``: the relative residual at which each step's conjugate gradients stop;
    ``cg_max_steps``: their most iterations (static). The four tolerances may be arrays, as
    `pbrfit.fitting.runner.Runner` passes them, so that one program serves every tolerance.

    ``options["carry"]``, an `LMCarry`, goes on from where an earlier run of the same solve
    stopped (its x is the start): the run's first call to `step` linearises there and takes no
    step, and the budget still counts the steps from the solve's start.
    """

    rtol: Any = RTOL
    atol: Any = ATOL
    cg_rtol: Any = CG_RTOL
    noise_rtol: Any = NOISE_RTOL
    cg_max_steps: int = eqx.field(static=True, default=CG_MAX_STEPS)
    norm: Callable = optx.max_norm

    def init(self, fn, y, args: Problem, options, f_struct, aux_struct, tags) -> _StructuredLMState:
        del fn, f_struct, aux_struct, tags
        # The first step only linearises at the start (no step is taken: every channel inactive),
        # so the linearisation is traced once, inside the loop.
        k = y.shape[-1]
        options = options or {}
        budget = options.get("max_steps")
        budget = jnp.asarray(_NO_BUDGET if budget is None else budget, jnp.int32)
        carry = options.get("carry")
        carry = LMCarry.start(y.dtype) if carry is None else carry
        r = jnp.zeros((args.num_pixels, 3), y.dtype)
        jac = jnp.zeros((args.index.shape[0], 3, k), y.dtype)
        # JᵀJ's blocks and factors are made by the first step from the iterate (`stale`)
        shapes = jax.eval_shape(lambda j: gauss_newton_operator(j, args, args.stencil), jac)
        blocks, factors = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)
        return _StructuredLMState(
            r=r, jac=jac, loss=jnp.asarray(jnp.inf, y.dtype), g=jnp.zeros_like(y), blocks=blocks, factors=factors,
            stale=jnp.asarray(True), lam=jnp.asarray(carry.lam, y.dtype), nu=jnp.asarray(carry.nu, y.dtype),
            k=jnp.asarray(carry.k, jnp.int32), done=jnp.asarray(False),
            accepted=jnp.asarray(carry.accepted, jnp.int32), cg=jnp.asarray(carry.cg, jnp.int32), budget=budget,
            history=jnp.asarray(carry.history, y.dtype), fresh=jnp.asarray(True))

    def step(self, fn, y, args: Problem, options, state: _StructuredLMState, tags):
        del fn, tags
        problem, x = args, y
        k = x.shape[-1]
        lo, hi = jnp.asarray(lower(k), x.dtype), jnp.asarray(upper(k), x.dtype)
        eye = jnp.eye(k, dtype=x.dtype)
        loss, lam, nu = state.loss, state.lam, state.nu
        # the first call of a run only linearises at its start: the solve's start (k = 0), or
        # where an earlier run of it stopped (k > 0: then it counts no call and keeps no E)
        first = state.fresh
        again = first & (state.k > 0)
        st = args.stencil

        def assemble():  # JᵀJ and g at the iterate, once: a rejected step leaves them as they are
            blocks, factors = gauss_newton_operator(state.jac, problem, st)
            return gradient(state.r, state.jac, x, problem), blocks, factors

        def take_step():
            g, blocks, factors = lax.cond(state.stale, assemble, lambda: (state.g, state.blocks, state.factors))

            def product(v):
                return gauss_newton_product(factors, v, problem, st)

            a = _active(x, g, problem.free)
            diag = jnp.diagonal(blocks, axis1=1, axis2=2)
            mean_diag = jnp.sum(diag * problem.free) / jnp.maximum(jnp.sum(problem.free), 1.0)
            damp = diag + DAMPING_FLOOR * mean_diag

            def m_of(a, blocks, damp):  # M's diagonal blocks: damped where active, the identity's elsewhere
                outer = a[:, :, None] * a[:, None, :]
                return outer * (blocks + lam * damp[:, :, None] * eye) + (1.0 - a)[:, :, None] * eye

            if st is None:
                m_inv = spd_block_inverse(m_of(a, blocks, damp))

                def matvec(v):
                    av = a * v
                    return a * (product(av) + lam * damp * av) + (1.0 - a) * v
            else:  # the same operator by stencil: its blocks masked to the active channels, M's on the diagonal
                # (over `Problem.texels` alone where given: every other texel's row is the identity's,
                # its right-hand side 0, and its solution 0)
                rows, nb, a_nb = _stencil_rows(problem, st, a)
                a_rows = _rows(a, rows)
                m_blocks = m_of(a_rows, _rows(blocks, rows), _rows(damp, rows))
                m_inv = spd_block_inverse(m_blocks)
                masked = (a_rows[:, None, :, None] * _rows(factors, rows)
                          * a_nb[nb][:, :, None, :]).at[:, st.centre].set(m_blocks)

                def matvec(v):
                    return stencil_product(masked, nb, _with_zero_row(v, rows))

            def precond(v):
                return jnp.sum(m_inv * v[:, None, :], axis=2)

            if st is None:
                delta, iters = pcg(matvec, -a * g, precond, self.cg_rtol, self.cg_max_steps)
            else:
                delta, iters = pcg(matvec, _rows(-a * g, rows), precond, self.cg_rtol, self.cg_max_steps)
                delta = delta if problem.texels is None else jnp.zeros_like(x).at[rows].set(delta, mode="drop")
            x_new = jnp.clip(x + a * delta, lo, hi)
            step = x_new - x
            predicted = -(_vdot(g, step) + 0.5 * _vdot(step, product(step)))
            return x_new, predicted, jnp.asarray(iters, jnp.int32), (g, blocks, factors)

        def stay():  # the first call: every channel inactive, no products (x clipped into the box)
            return (jnp.clip(x, lo, hi), jnp.zeros((), x.dtype), jnp.asarray(0, jnp.int32),
                    (state.g, state.blocks, state.factors))

        x_new, predicted, iters, (g_new, blocks_new, factors_new) = lax.cond(first, stay, take_step)
        step = x_new - x
        r_new, jac_new, trial = linearize(x_new, problem)
        # step 0 only linearises at the start: kept even where the loss is not finite (an
        # overflow), so that the returned residuals and loss are the start's and the caller sees
        # it, not zeros and inf
        accept = first | (jnp.isfinite(trial) & (trial < loss))

        pick = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        r_new, jac_new, loss_new = pick(r_new, state.r), pick(jac_new, state.jac), pick(trial, loss)
        actual = jnp.where(first, 0.0, loss - trial)
        rho = actual / jnp.maximum(predicted, jnp.finfo(x.dtype).tiny)
        lam_new = jnp.where(accept, lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), lam * nu)
        nu_new = jnp.where(accept, 2.0, 2.0 * nu)
        moved = self.norm(step)
        # a step, accepted or not, whose predicted and actual changes of E are both within rtol · E
        # ends the solve (MINPACK's ftol test): E is at its float32 floor, where λ would otherwise
        # grow over rejected steps until the step is within atol
        tol = self.rtol * loss
        floor = (predicted <= tol) & (jnp.abs(actual) <= tol)
        # E at the targets' float32 rounding: no step can tell anything more from the images
        rounded = loss_new <= rounding_floor(problem)
        # a step that gains less than noise_rtol · p σ̂² / 2: the maps move by less than their noise
        # (σ̂² = 2 E / (n - p), as the host's `pbrfit.fitting.uncertainty.residual_variance`)
        free = jnp.sum(problem.free)
        sigma2 = 2.0 * loss / jnp.maximum(3.0 * (problem.num_pixels + problem.left("pixels")) - free, 1.0)
        noise_tol = self.noise_rtol * free * sigma2 / 2.0
        noise = accept & (actual <= noise_tol) & (predicted <= noise_tol)
        done = ~first & ((accept & (actual <= tol)) | noise | floor | rounded | (moved <= self.atol)
                         | (lam_new > LAMBDA_MAX))
        lam_new = jnp.where(first, lam, lam_new)
        nu_new = jnp.where(first, nu, nu_new)
        history = jnp.where(again, state.history, state.history.at[state.k].set(loss_new, mode="drop"))
        new_state = _StructuredLMState(
            r=r_new, jac=jac_new, loss=loss_new, g=g_new, blocks=blocks_new, factors=factors_new, stale=accept,
            lam=lam_new, nu=nu_new, k=state.k + (~again).astype(state.k.dtype), done=done,
            accepted=state.accepted + (accept & ~first).astype(jnp.int32), cg=state.cg + iters, budget=state.budget,
            history=history, fresh=jnp.asarray(False))
        return jnp.where(accept, x_new, x), new_state, None

    def terminate(self, fn, y, args, options, state: _StructuredLMState, tags):
        del fn, y, args, options, tags
        return state.done | (state.k > state.budget), optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state: _StructuredLMState, tags, result):
        del fn, args, options, tags, result
        return y, aux, dict(steps=jnp.maximum(state.k - 1, 0), accepted=state.accepted, cg_iterations=state.cg,
                            loss=state.loss, damping=state.lam, history=state.history, nu=state.nu, calls=state.k,
                            stopped=state.done)


def _residuals(x, problem: Problem):
    return residuals(x, problem)


@eqx.filter_jit
def solve(x0: Float[Array, "T K"], problem: Problem, solver: StructuredLM = StructuredLM(), max_steps=50,
          carry: LMCarry | None = None):
    """`solver` on `problem` from texel values x0 through `optx.least_squares`, at most
    `max_steps` steps (an int32 array: one compiled program serves every budget; 0 only
    linearises at x0). ``carry``: go on from an earlier run that stopped at x0 and returned
    stats s (``LMCarry.after(s)``; its budget counts from that solve's start): the steps are
    those one run to the last budget takes, bit for bit.

    Returns (x, LMStats, residuals (P, 3), per-row Jacobians (R, 3, K); R = P with one sample per
    pixel) at the returned x."""
    sol = optx.least_squares(_residuals, solver, x0, args=problem,
                             options=dict(max_steps=jnp.asarray(max_steps, jnp.int32), carry=carry),
                             max_steps=None, throw=False)
    s = sol.stats
    stats = LMStats(s["steps"], s["accepted"], s["cg_iterations"], s["loss"], s["damping"], s["history"], s["nu"],
                    s["calls"], s["stopped"])
    return sol.value, stats, sol.state.r, sol.state.jac
