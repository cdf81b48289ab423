"""The linear solver inside the optimistix least-squares solvers (`pbrfit.fitting.solvers.optx.truncated_cg`)."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np

from pbrfit.fitting.solvers.optx import CG_MAX_STEPS, truncated_cg


def _solve(diagonal, b, max_steps=CG_MAX_STEPS):
    operator = lx.DiagonalLinearOperator(jnp.asarray(diagonal, jnp.float32))
    operator = lx.TaggedLinearOperator(operator, lx.positive_semidefinite_tag)
    solver = truncated_cg()(rtol=1e-3, atol=1e-8, max_steps=max_steps)
    return lx.linear_solve(operator, jnp.asarray(b, jnp.float32), solver, throw=False)


def test_small_curvatures_of_a_large_float32_system_are_solved():
    """Every curvature of this 20,000-unknown float32 system is under lineax's CG breakdown
    threshold (100 · N · eps ≈ 0.24 of rᵀr: its CG returns NaN at the first step, which ended
    `lm` after 3 of 20 steps on the peer preset). Truncated CG solves it to its tolerance."""
    n = 20_000
    diagonal = np.linspace(0.01, 0.05, n)
    b = np.random.default_rng(0).normal(size=n)
    sol = _solve(diagonal, b)
    assert sol.result == lx.RESULTS.successful
    y = np.asarray(sol.value)
    assert np.all(np.isfinite(y))
    np.testing.assert_allclose(y, b / diagonal, rtol=1e-2, atol=1e-3)


def test_the_step_limit_gives_the_last_iterate_as_a_success():
    """At `max_steps` the iterate is the step (inexact Gauss-Newton), and it lowers the quadratic
    model ½ yᵀAy − bᵀy below its value at 0."""
    diagonal = np.geomspace(1e-3, 1.0, 500)
    b = np.ones(500)
    sol = _solve(diagonal, b, max_steps=5)
    assert sol.result == lx.RESULTS.successful and int(sol.stats["num_steps"]) == 5
    y = np.asarray(sol.value, float)
    assert 0.5 * y @ (diagonal * y) - b @ y < -0.1
    assert not np.allclose(y, b / diagonal, rtol=0.1)  # five steps do not solve it


def test_negative_curvature_keeps_the_last_iterate():
    """A curvature pᵀAp ≤ 0 (an operator that is not what its tag says, or rounding) ends the CG
    with the last iterate: here the first, y = (bᵀb / bᵀAb) b = 1.5 b; the second direction
    p = (3, 1.5, 6) has pᵀAp = −22.5."""
    sol = _solve([1.0, 2.0, -1.0], [1.0, 1.0, 1.0])
    assert sol.result == lx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(sol.value), [1.5, 1.5, 1.5], rtol=1e-6)
    assert int(sol.stats["num_steps"]) == 2


def test_a_well_conditioned_system_converges_before_the_step_limit():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(30, 30))
    a = m @ m.T / 30 + np.eye(30)
    b = rng.normal(size=30)
    operator = lx.MatrixLinearOperator(jnp.asarray(a, jnp.float32), lx.positive_semidefinite_tag)
    sol = lx.linear_solve(operator, jnp.asarray(b, jnp.float32), truncated_cg()(rtol=1e-5, atol=1e-8, max_steps=100))
    assert int(sol.stats["num_steps"]) < 60
    np.testing.assert_allclose(np.asarray(sol.value), np.linalg.solve(a, b), rtol=1e-3, atol=1e-4)
    # negative definite: lineax's CG solves -A y = -b and turns the sign back
    operator = lx.MatrixLinearOperator(jnp.asarray(-a, jnp.float32), lx.negative_semidefinite_tag)
    sol = lx.linear_solve(operator, jnp.asarray(b, jnp.float32), truncated_cg()(rtol=1e-5, atol=1e-8, max_steps=100))
    np.testing.assert_allclose(np.asarray(sol.value), np.linalg.solve(-a, b), rtol=1e-3, atol=1e-4)


def test_normal_equations_of_a_tuple_of_residuals():
    """As the optimistix solvers use it: `lx.Normal` over a Jacobian whose output is a pytree
    (pbrfit's (data, prior) residuals); the step is the least-squares solution."""
    rng = np.random.default_rng(2)
    j1, j2 = rng.normal(size=(40, 6)), rng.normal(size=(9, 6))
    b1, b2 = rng.normal(size=40), rng.normal(size=9)
    operator = lx.FunctionLinearOperator(lambda z: (jnp.asarray(j1, jnp.float32) @ z, jnp.asarray(j2, jnp.float32) @ z),
                                         jax.ShapeDtypeStruct((6,), jnp.float32))
    solver = lx.Normal(truncated_cg()(rtol=1e-6, atol=1e-9, max_steps=50))
    sol = lx.linear_solve(operator, (jnp.asarray(b1, jnp.float32), jnp.asarray(b2, jnp.float32)), solver)
    expected = np.linalg.lstsq(np.vstack([j1, j2]), np.concatenate([b1, b2]), rcond=None)[0]
    np.testing.assert_allclose(np.asarray(sol.value), expected, rtol=1e-3, atol=1e-4)


def test_a_non_finite_right_hand_side_gives_no_step():
    sol = _solve([1.0, 2.0], [np.inf, 1.0])
    assert sol.result == lx.RESULTS.successful
    np.testing.assert_array_equal(np.asarray(sol.value), [0.0, 0.0])
