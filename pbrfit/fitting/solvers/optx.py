"""The fit's objective under the general-purpose optimistix solvers.

These solvers know nothing of bounds or of the problem's block structure, so they work on the
sine storage of `pbrfit.fitting.parameters` (``value = lo + (hi - lo)(1 + sin z)/2``, bounds reached at
finite z) with the fixed and unobserved channels masked back to their values, and see the
residuals of `pbrfit.fitting.objective.residuals` as a black box. `make_solver` makes them by name
(`pbrfit.fitting.solvers.names`); a user's own optimistix solver runs through the same `optx_solve`:

- ``lm``: `optx.LevenbergMarquardt` with a matrix-free normal-equations CG (`lx.Normal(lx.CG)`);
  its default QR would materialise the (pixels × parameters) Jacobian.
- ``gn``: `optx.GaussNewton` with the same matrix-free linear solver.
- ``dogleg``: `optx.Dogleg` (trust region), same linear solver.
- ``bfgs``: `optx.BFGS` (dense inverse Hessian), run as `optx.LBFGS` above `BFGS_MAX_PARAMETERS`
  unknowns (`for_size`: a dense N × N matrix at 20,000 unknowns is 1.6 GB); ``lbfgs`` asks for
  L-BFGS directly.
- ``ncg``: `optx.NonlinearCG`;  ``adam``: `optx.OptaxMinimiser(optax.adam)`.

The CG of the three least-squares solvers is pbrfit's own truncated CG (`truncated_cg`): after
`CG_MAX_STEPS`, or at a curvature rounding makes non-positive, its last iterate is taken as the
step, as inexact (truncated) Gauss-Newton methods take it (Nocedal & Wright 2006, ch. 7: every CG
iterate on the normal equations from 0 lowers the linear model). lineax's CG reports the step
limit as a failure, which ended the solve (on the peer preset at 64 × 64, 20 steps, ``dogleg``
stopped after 2 steps at roughness RMSE 0.021), and declares breakdown below a curvature
threshold that grows with the number of unknowns times float32's epsilon, which ended ``lm``
after 3 steps there (roughness 0.024; it now runs its 20 to 0.009, ``gn`` to 0.0015, ``dogleg``
to 0.010). The solvers are told not to throw: a failure ends the solve, reported in its result.
"""

from __future__ import annotations

import functools
from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optax
import optimistix as optx
from jax.flatten_util import ravel_pytree

from ..defaults import OPTX_SOLVERS
from ..parameters import from_sine, lower, to_sine, upper
from ..objective import Problem, residuals

__all__ = ["OPTX_SOLVERS", "BFGS_MAX_PARAMETERS", "ADAM_LEARNING_RATE", "START_MARGIN", "make_solver", "for_size",
           "optx_solve", "truncated_cg"]

#: Above this many unknowns "bfgs" uses L-BFGS: the dense inverse Hessian grows as N².
BFGS_MAX_PARAMETERS = 4096
#: Adam's step in the sine storage (radians): 0.02 moves a mid-range value by about 1% per step.
ADAM_LEARNING_RATE = 0.02
#: CG steps per linear solve inside the optimistix least-squares solvers.
CG_MAX_STEPS = 100
#: The start is moved this share of each channel's range inside its bounds. In the sine storage
#: d value / dz = (hi - lo) cos(z) / 2 vanishes at a bound, so a channel started on one (the grid
#: start puts metallic at exactly 0 or 1, the prior at 0) never moves: on the flash preset at
#: 8 × 8, `lm` from the prior left 21 of 23 metal texels at 0. At 1e-3 of the range the
#: derivative is 6% of its largest.
START_MARGIN = 1e-3


def _dot(a, b):
    """aᵀb as a sum of products: exact in the input precision on every backend (a dot_general
    at JAX's default precision is TF32 on GPUs)."""
    return jnp.sum(a * b)


@functools.cache
def truncated_cg():
    """The class ``TruncatedCG(rtol, atol, max_steps)``: conjugate gradients on a positive
    semidefinite operator A (here JᵀJ + λI, through `lx.Normal`) for the step of an inexact
    Gauss-Newton method (Nocedal & Wright 2006, §7.1; Steihaug 1983). From y₀ = 0, with
    r₀ = p₀ = b:

        α = rᵀr / pᵀAp,   y ← y + α p,   r ← r − α A p,   p ← r + (r'ᵀr' / rᵀr) p

    until ‖r / (rtol |b| + atol)‖ ≤ 1 and ‖Δy / (rtol |y| + atol)‖ ≤ 1 in the solver's `norm`
    (lineax's test; the max norm by default), or `max_steps` (default 10 N, as lineax's), r
    recomputed as b − Ay every `stabilise_every` steps (lineax's default 10: without it the
    float32 steps differ). Every iterate lowers the quadratic model, so the last one is a step
    wherever the loop ends: at the step limit, and where a curvature pᵀAp is not positive or a
    value is not finite (rounding in float32) the last finite iterate is kept, as truncated CG
    keeps it. Both are reported as successes.

    lineax's own `CG` reports the step limit as a failure and declares breakdown (NaN) where
    pᵀAp < 100 · N · eps · rᵀr, a threshold that grows with the number of unknowns N: in float32
    at 20,000 unknowns every curvature under 0.24 breaks down, which ended `lm` after 3 of its 20
    steps on the peer preset at 64 × 64 and `gn` after 11. Made on first use, so that lineax is
    imported only by the solvers that need it."""
    class TruncatedCG(lx.CG):
        def compute(self, state, vector, options):
            if options.get("preconditioner") is not None or options.get("y0") is not None:
                raise ValueError("TruncatedCG starts at 0 and takes no preconditioner")
            operator, is_nsd = state
            b, unravel = ravel_pytree(vector)
            max_steps = 10 * b.size if self.max_steps is None else self.max_steps
            stats = {"num_steps": jnp.asarray(0), "max_steps": self.max_steps}
            if b.size == 0:
                return vector, lx.RESULTS.successful, stats

            def mv(v):
                return ravel_pytree(operator.mv(unravel(v)))[0]

            scale = self.rtol * jnp.abs(b) + self.atol

            def cond(carry):
                y, r, _, _, diff, step, done = carry
                y_scale = self.rtol * jnp.abs(y) + self.atol
                converged = (self.norm(r / scale) <= 1) & (self.norm(diff / y_scale) <= 1)
                return ~done & (step < max_steps) & ~converged

            def body(carry):
                y, r, p, gamma, diff, step, _ = carry
                ap = mv(p)
                curvature = _dot(p, ap)
                alpha = gamma / jnp.where(curvature > 0, curvature, 1)
                y_next = y + alpha * p
                if self.stabilise_every is None:
                    r_next = r - alpha * ap
                else:  # the residual recomputed from y, against rounding
                    r_next = jax.lax.cond((step + 1) % self.stabilise_every == 0, lambda: b - mv(y_next),
                                          lambda: r - alpha * ap)
                gamma_next = _dot(r_next, r_next)
                ok = (curvature > 0) & jnp.isfinite(gamma_next) & jnp.all(jnp.isfinite(y_next))
                p_next = r_next + (gamma_next / gamma) * p
                keep = lambda new, old: jnp.where(ok, new, old)  # noqa: E731
                return (keep(y_next, y), keep(r_next, r), keep(p_next, p), keep(gamma_next, gamma), keep(alpha * p, diff),
                        step + 1, ~ok)

            gamma0 = _dot(b, b)
            carry = (jnp.zeros_like(b), b, b, gamma0, jnp.full_like(b, jnp.inf), 0, ~jnp.isfinite(gamma0))
            y, _, _, _, _, steps, _ = jax.lax.while_loop(cond, body, carry)
            if is_nsd.value:
                y = -y
            return unravel(y), lx.RESULTS.successful, {**stats, "num_steps": steps}

    return TruncatedCG


@functools.lru_cache(maxsize=64)
def make_solver(name: str, rtol: float, atol: float):
    """The optimistix solver named `name` (one of `OPTX_SOLVERS`; see the module docstring). One
    object per name and tolerances, so that `pbrfit.fitting.solvers.names.solver_name` knows it
    again (optax's transformations compare by identity)."""
    # optimistix, lineax and optax are imported here, not with the module: they cost every fit
    # that runs none of these solvers about 0.4 s of imports.

    cg = lx.Normal(truncated_cg()(rtol=1e-3, atol=1e-8, max_steps=CG_MAX_STEPS))
    if name == "lm":
        return optx.LevenbergMarquardt(rtol, atol, linear_solver=cg)
    if name == "gn":
        return optx.GaussNewton(rtol, atol, linear_solver=cg)
    if name == "dogleg":
        return optx.Dogleg(rtol, atol, linear_solver=cg)
    if name == "bfgs":
        return optx.BFGS(rtol, atol)
    if name == "lbfgs":
        return optx.LBFGS(rtol, atol)
    if name == "ncg":
        return optx.NonlinearCG(rtol, atol)
    if name == "adam":
        return optx.OptaxMinimiser(optax.adam(ADAM_LEARNING_RATE), rtol, atol)
    raise ValueError(f"unknown solver {name!r}; expected one of {', '.join(OPTX_SOLVERS)}")


def for_size(solver, num_parameters: int):
    """`solver` as it runs on `num_parameters` unknowns: an `optx.BFGS` above
    `BFGS_MAX_PARAMETERS` becomes an `optx.LBFGS` with its tolerances (its dense inverse Hessian
    grows as N²); every other solver as it is."""
    if type(solver) is optx.BFGS and num_parameters > BFGS_MAX_PARAMETERS:
        return optx.LBFGS(solver.rtol, solver.atol, solver.norm)
    return solver


def _values(z, x_fixed, problem: Problem):
    return jnp.where(problem.free > 0, from_sine(z), x_fixed)


@eqx.filter_jit
def optx_solve(x0, problem: Problem, solver, max_steps: int, progress: Optional[Callable] = None):
    """Run an optimistix solver (an `optx.AbstractLeastSquaresSolver` on the residuals, or an
    `optx.AbstractMinimiser` on ½ Σ r²) from texel values x0; returns (x, steps, result code).

    ``progress(loss)``, when given, is called on the host with the objective ½ Σ r² at every
    evaluation of it (``jax.debug.callback``): optimistix's solvers keep their steps to
    themselves, and an evaluation is what a step of each of them costs (line searches and trust
    regions evaluate rejected points too)."""
    k = x0.shape[-1]
    lo, hi = jnp.asarray(lower(k), x0.dtype), jnp.asarray(upper(k), x0.dtype)
    inset = START_MARGIN * (hi - lo)
    z0 = to_sine(jnp.clip(x0, lo + inset, hi - inset))  # fixed channels keep x0 (`_values`)

    def res(z, args):
        r, s = residuals(_values(z, x0, problem), problem)
        if progress is not None:
            jax.debug.callback(progress, 0.5 * (jnp.sum(r * r) + jnp.sum(s * s)))
        return r, s

    def loss(z, args):
        r, s = res(z, args)
        return 0.5 * (jnp.sum(r * r) + jnp.sum(s * s))

    # optimistix, lineax and optax contract at JAX's default precision, which is TF32 on GPUs;
    # the fit's float32 contractions all run at full precision (`pbrfit.fitting.objective`, `pbrfit.fitting.normal_matrix`).
    with jax.default_matmul_precision("highest"):
        if isinstance(solver, optx.AbstractLeastSquaresSolver):
            sol = optx.least_squares(res, solver, z0, max_steps=max_steps, throw=False)
        else:
            sol = optx.minimise(loss, solver, z0, max_steps=max_steps, throw=False)
    x = _values(sol.value, x0, problem)
    return x, sol.stats["num_steps"], sol.result._value
