"""The structured solver as an optimistix solver: `StructuredLM` (`pbrfit.fitting.solvers.structured`)
run through `optx.least_squares`.

The small problem is `test_sharding`'s: a plane under two lights, 1001 pixels, a 4 × 4 map,
metallic held, targets rendered from a random material plus noise."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from pbrfit.fitting.initialisation import grid_initialise
from pbrfit.fitting.objective import linearize, residuals
from pbrfit.fitting.parameters import lower, upper
from pbrfit.fitting.solvers.structured import StructuredLM, solve
from test_sharding import _problem, _start

# The hand-written loop this solver replaced (a jitted lax.while_loop), on `_problem` from the
# grid start with rtol 1e-7 and atol 1e-6, 30 steps at most: (steps, accepted, CG iterations),
# E, λ and the mean of each channel of x (CPU, float32). With the prior (smooth 1e-3) three steps
# are accepted, then eight are refused until λ passes LAMBDA_MAX; without it the fifth accepted
# step is small enough to stop.
REFERENCE = {
    1e-3: ((11, 3, 115), 0.14778105914592743, 2545166.0, (0.57315881, 0.46256701, 0.55512854, 0.0, 0.48584193)),
    0.0: ((5, 5, 62), 0.14532418549060822, 4.115227056900039e-06, (0.5731611, 0.46256968, 0.55513157, 0.0, 0.48588595)),
}


@pytest.fixture(scope="module", params=sorted(REFERENCE))
def start(request):
    problem, _ = _problem(smooth=request.param)
    return request.param, problem, grid_initialise(_start(problem), problem)


def test_structured_lm_steps_as_the_loop_it_replaced(start):
    smooth, problem, x0 = start
    (steps, accepted, cg), loss, damping, mean = REFERENCE[smooth]
    seen = []
    sol = optx.least_squares(lambda x, p: residuals(x, p), StructuredLM(rtol=1e-7, atol=1e-6), x0, args=problem,
                             options=dict(max_steps=jnp.asarray(30, jnp.int32), progress=lambda k, e: seen.append(int(k))),
                             max_steps=None, throw=False)
    jax.block_until_ready(sol.value)
    s = sol.stats
    assert (int(s["steps"]), int(s["accepted"]), int(s["cg_iterations"])) == (steps, accepted, cg)
    assert int(s["num_steps"]) == steps + 1  # optimistix counts the first call, which only linearises
    assert float(s["loss"]) == pytest.approx(loss, rel=1e-5) and float(s["damping"]) == pytest.approx(damping, rel=1e-3)
    np.testing.assert_allclose(np.asarray(sol.value, np.float64).mean(0), mean, atol=1e-6)
    assert sol.result == optx.RESULTS.successful
    assert seen == list(range(steps + 1))  # progress at every step, the start's E first
    # the residuals and Jacobians at the returned x are in the final state
    r, jac, e = jax.jit(linearize)(sol.value, problem)
    np.testing.assert_allclose(np.asarray(sol.state.r), np.asarray(r), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(sol.state.jac), np.asarray(jac), rtol=1e-5, atol=1e-6)
    assert float(e) == pytest.approx(float(s["loss"]), rel=1e-6)


def test_one_program_serves_every_step_budget(start):
    smooth, problem, x0 = start
    solver = StructuredLM(rtol=1e-7, atol=1e-6)
    compiled = solve.lower(x0, problem, solver, jnp.asarray(0, jnp.int32)).compile()
    x, stats, r, jac = compiled(x0, problem, solver, jnp.asarray(0, jnp.int32))
    # 0 steps only linearises, at the start clipped into the box (the runner's Jacobian)
    clipped = jnp.clip(x0, jnp.asarray(lower(5)), jnp.asarray(upper(5)))
    np.testing.assert_array_equal(np.asarray(x), np.asarray(clipped))
    assert int(stats.steps) == 0 and int(stats.accepted) == 0
    np.testing.assert_allclose(np.asarray(jac), np.asarray(jax.jit(linearize)(clipped, problem)[1]), rtol=1e-5, atol=1e-6)
    x2, stats2, *_ = compiled(x0, problem, solver, jnp.asarray(2, jnp.int32))
    assert int(stats2.steps) == 2 and float(stats2.loss) < float(stats.loss)
    _, stats30, *_ = compiled(x0, problem, solver, jnp.asarray(30, jnp.int32))
    assert int(stats30.steps) == REFERENCE[smooth][0][0]


def test_without_a_budget_optimistix_max_steps_bounds_the_solve(start):
    _, problem, x0 = start
    sol = optx.least_squares(lambda x, p: residuals(x, p), StructuredLM(rtol=1e-7, atol=1e-6), x0, args=problem,
                             max_steps=3, throw=False)
    assert int(sol.stats["num_steps"]) == 3 and int(sol.stats["steps"]) == 2
    assert sol.result == optx.RESULTS.nonlinear_max_steps_reached
