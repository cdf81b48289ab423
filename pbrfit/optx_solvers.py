"""The fit's objective under the general-purpose optimistix solvers.

These solvers know nothing of bounds or of the problem's block structure, so they work on the
sine storage of `pbrfit.parameters` (``value = lo + (hi - lo)(1 + sin z)/2``, bounds reached at
finite z) with the fixed and unobserved channels masked back to their values, and see the
residuals of `pbrfit.solvers.residuals` as a black box:

- ``lm``: `optx.LevenbergMarquardt` with a matrix-free normal-equations CG (`lx.Normal(lx.CG)`);
  its default QR would materialise the (pixels × parameters) Jacobian.
- ``gn``: `optx.GaussNewton` with the same matrix-free linear solver.
- ``dogleg``: `optx.Dogleg` (trust region), same linear solver.
- ``bfgs``: `optx.BFGS` (dense inverse Hessian) up to `BFGS_MAX_PARAMETERS` unknowns, else
  `optx.LBFGS` (a dense N × N matrix at 20,000 unknowns is 1.6 GB); ``lbfgs`` asks for it directly.
- ``ncg``: `optx.NonlinearCG`;  ``adam``: `optx.OptaxMinimiser(optax.adam)`.

The CG of the three least-squares solvers is truncated (`truncated_cg`): after `CG_MAX_STEPS`
its iterate is taken as the step, as inexact (truncated) Gauss-Newton methods take it (Nocedal
& Wright 2006, ch. 7: every CG iterate on the normal equations from 0 lowers the linear model).
lineax reports those steps as a failure, which ended the solve: on the peer preset at 64 × 64
(20 steps) ``dogleg`` stopped after 2 steps at roughness RMSE 0.021, and with the truncation
runs its 20 to 0.002; ``gn`` reaches 0.003.

lineax's CG declares breakdown when a curvature falls below a threshold that scales with the
problem size times float32's epsilon, which the normal equations of a large float32 problem
hit; these solvers therefore run in float64 when ``jax_enable_x64`` is on, and are otherwise
told not to throw (a breakdown ends the solve, reported in its result).
"""

from __future__ import annotations

import functools
from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp

from .parameters import from_sine, lower, to_sine, upper
from .solvers import Problem, residuals

__all__ = ["OPTX_SOLVERS", "BFGS_MAX_PARAMETERS", "ADAM_LEARNING_RATE", "START_MARGIN", "make_solver", "optx_solve",
           "truncated_cg"]

OPTX_SOLVERS = ("lm", "gn", "dogleg", "bfgs", "lbfgs", "ncg", "adam")
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


@functools.cache
def truncated_cg():
    """The class ``TruncatedCG(inner)``: a lineax solver that runs ``inner`` (a CG) and reports its
    iterate at the step limit as a success, the step of a truncated Gauss-Newton method (module
    docstring); any other failure (breakdown, non-finite values) stays one. Made on first use,
    so that lineax is imported only by the solvers that need it."""
    import lineax as lx

    class TruncatedCG(lx.AbstractLinearSolver):
        inner: lx.AbstractLinearSolver

        def init(self, operator, options):
            return self.inner.init(operator, options)

        def compute(self, state, vector, options):
            solution, result, stats = self.inner.compute(state, vector, options)
            result = lx.RESULTS.where(result == lx.RESULTS.max_steps_reached, lx.RESULTS.successful, result)
            return solution, result, stats

        def transpose(self, state, options):
            return self.inner.transpose(state, options)

        def conj(self, state, options):
            return self.inner.conj(state, options)

        def assume_full_rank(self):
            return self.inner.assume_full_rank()

    return TruncatedCG


def make_solver(name: str, rtol: float, atol: float, num_parameters: int):
    """The optimistix solver for `name` (see the module docstring) and whether it is least squares."""
    # optimistix, lineax and optax are imported here, not with the module: the default solver
    # never needs them, and they cost every fit about 0.4 s of imports.
    import lineax as lx
    import optax
    import optimistix as optx

    cg = truncated_cg()(lx.Normal(lx.CG(rtol=1e-3, atol=1e-8, max_steps=CG_MAX_STEPS)))
    if name == "lm":
        return optx.LevenbergMarquardt(rtol, atol, linear_solver=cg), True
    if name == "gn":
        return optx.GaussNewton(rtol, atol, linear_solver=cg), True
    if name == "dogleg":
        return optx.Dogleg(rtol, atol, linear_solver=cg), True
    if name == "bfgs" and num_parameters <= BFGS_MAX_PARAMETERS:
        return optx.BFGS(rtol, atol), False
    if name in ("bfgs", "lbfgs"):
        return optx.LBFGS(rtol, atol), False
    if name == "ncg":
        return optx.NonlinearCG(rtol, atol), False
    if name == "adam":
        return optx.OptaxMinimiser(optax.adam(ADAM_LEARNING_RATE), rtol, atol), False
    raise ValueError(f"unknown solver {name!r}; expected one of {', '.join(OPTX_SOLVERS)}")


def _values(z, x_fixed, problem: Problem):
    return jnp.where(problem.free > 0, from_sine(z), x_fixed)


@eqx.filter_jit
def optx_solve(x0, problem: Problem, solver, least_squares: bool, max_steps: int,
               progress: Optional[Callable] = None):
    """Run an optimistix solver from texel values x0; returns (x, steps, result code).

    ``progress(loss)``, when given, is called on the host with the objective ½ Σ r² at every
    evaluation of it (``jax.debug.callback``): optimistix's solvers keep their steps to
    themselves, and an evaluation is what a step of each of them costs (line searches and trust
    regions evaluate rejected points too)."""
    import optimistix as optx

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
    # the fit's float32 contractions all run at full precision (`pbrfit.solvers`).
    with jax.default_matmul_precision("highest"):
        if least_squares:
            sol = optx.least_squares(res, solver, z0, max_steps=max_steps, throw=False)
        else:
            sol = optx.minimise(loss, solver, z0, max_steps=max_steps, throw=False)
    x = _values(sol.value, x0, problem)
    return x, sol.stats["num_steps"], sol.result._value
