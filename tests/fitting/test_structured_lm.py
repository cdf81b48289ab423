"""The fit's solvers as optimistix solvers: `pbrfit.StructuredLM` (`pbrfit.fitting.solvers.structured`)
run through `optx.least_squares`, the names of `pbrfit.fitting.solvers.names`, and a user's own
optimistix solver in `pbrfit.fit` and on the command line.

The small problem is `test_sharding`'s: a plane under two lights, 1001 pixels, a 4 × 4 map,
metallic held, targets rendered from a random material plus noise."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import pbrfit
from pbrfit.fitting.initialisation import grid_initialise
from pbrfit.fitting.objective import linearize, pixel_residuals, residuals, rounding_floor
from pbrfit.fitting.options import FitOptions
from pbrfit.fitting.parameters import lower, upper
from pbrfit.fitting.solvers.names import SOLVERS, is_structured, solver_for, solver_name
from pbrfit.fitting.solvers.structured import (ATOL, CG_RTOL, HISTORY, NOISE_RTOL, RTOL, LMCarry, StructuredLM,
                                                  solve)
from test_sharding import _problem, _start

# The solver on `_problem` from the grid start with rtol 1e-7 and atol 1e-6 and no noise-relative
# stop (the loop it replaced had none; `test_a_noisy_solve_stops_once_a_step_gains_less_than_its_noise`
# has it), 30 steps at most: E
# and the mean of each channel of x (CPU, float32). Both reach E's float32 floor at the third step
# and stop at the first step, accepted or refused, whose predicted and actual gains are both within
# rtol · E (before that test, the refused steps went on until λ passed LAMBDA_MAX: 11 steps with
# the prior, 3 accepted).
REFERENCE = {
    1e-3: (0.14778104424476624, (0.57315885, 0.46256703, 0.55512856, 0.0, 0.48584283)),
    0.0: (0.1453242152929306, (0.57316106, 0.46256966, 0.55513156, 0.0, 0.48588503)),
}
# ... that stop, as (steps, accepted), CG iterations and λ: at the fourth step, or at the fifth where
# the fourth, on the floor, still gains more than rtol · E in the last bits (λ a third lower after
# one more accepted step). Which one depends on the CPU's float32 rounding: an AMD EPYC stopped
# at the fourth without the prior and at the fifth with it, an Intel Xeon the other way round. On
# the floor the last step's CG iterations depend on that rounding too (the fifth: 60 to 62).
STOPS = {(4, 3): ((48, 48), 7.40740797482431e-05), (5, 4): ((60, 62), 2.4691360522410832e-05)}


def _stopped_as_before(steps, accepted, cg_iterations) -> bool:
    stop = STOPS.get((int(steps), int(accepted)))
    return stop is not None and stop[0][0] <= int(cg_iterations) <= stop[0][1]


@pytest.fixture(scope="module", params=sorted(REFERENCE))
def start(request):
    problem, _ = _problem(smooth=request.param)
    return request.param, problem, grid_initialise(_start(problem), problem)


def test_the_fit_options_hold_optimistix_solvers():
    solver = FitOptions().solver
    assert isinstance(solver, optx.AbstractLeastSquaresSolver) and isinstance(solver, StructuredLM)
    assert pbrfit.StructuredLM is StructuredLM and is_structured(solver)
    assert (solver.rtol, solver.atol, solver.cg_rtol, solver.noise_rtol) == (RTOL, ATOL, CG_RTOL, NOISE_RTOL)
    for name in SOLVERS:  # every name is an optimistix solver, and the report names it again
        made = FitOptions(solver=name).solver
        assert isinstance(made, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)), name
        assert solver_name(made) == name and (made.rtol, made.atol) == (RTOL, ATOL)
        assert is_structured(made) == (name == "structured")
    # the tolerance options set the solver's; a user's solver keeps its own unless they are given
    tuned = FitOptions(rtol=1e-7, atol=1e-4, cg_rtol=0.01, noise_rtol=0.1).solver
    assert (tuned.rtol, tuned.atol, tuned.cg_rtol, tuned.noise_rtol) == (1e-7, 1e-4, 0.01, 0.1)
    assert FitOptions(quality="best").solver.noise_rtol == 0.0 and FitOptions(solver="lm").noise_rtol is None
    assert FitOptions(solver="lm", atol=1e-3).solver == solver_for("lm", RTOL, 1e-3)
    own = optx.LevenbergMarquardt(rtol=1e-3, atol=1e-2)
    options = FitOptions(solver=own)
    assert options.solver is own and solver_name(own) == "LevenbergMarquardt"
    assert dataclasses.replace(options, max_steps=5).solver is own
    assert options.replace(rtol=1e-8).solver.rtol == 1e-8
    assert FitOptions(solver=StructuredLM(cg_rtol=0.1)).solver.cg_rtol == 0.1
    for bad, match in ((dict(solver=optx.Bisection(1e-6, 1e-6)), "solver: must be one of structured, lm"),
                       (dict(solver=StructuredLM(cg_rtol=2.0)), "cg_rtol: must be a number in"),
                       (dict(solver=StructuredLM(noise_rtol=-0.1)), "noise_rtol: must be a finite number >= 0"),
                       (dict(noise_rtol=float("inf")), "noise_rtol: must be a finite number >= 0"),
                       (dict(solver="lm", noise_rtol=0.1), "noise_rtol: only the structured solver uses it"),
                       (dict(solver=own, cg_rtol=0.1), "cg_rtol: only the structured solver uses it, not "
                                                       "solver='LevenbergMarquardt'")):
        with pytest.raises(ValueError, match=match):
            FitOptions(**bad)


def test_structured_lm_steps_as_the_loop_it_replaced(start):
    smooth, problem, x0 = start
    loss, mean = REFERENCE[smooth]
    sol = optx.least_squares(lambda x, p: residuals(x, p), StructuredLM(rtol=1e-7, atol=1e-6, noise_rtol=0.0), x0,
                             args=problem,
                             options=dict(max_steps=jnp.asarray(30, jnp.int32)),
                             max_steps=None, throw=False)
    jax.block_until_ready(sol.value)
    s = sol.stats
    counts = (int(s["steps"]), int(s["accepted"]), int(s["cg_iterations"]))
    assert _stopped_as_before(*counts), counts
    damping = STOPS[counts[:2]][1]
    steps = counts[0]
    assert int(s["num_steps"]) == steps + 1  # optimistix counts the first call, which only linearises
    assert float(s["loss"]) == pytest.approx(loss, rel=1e-5) and float(s["damping"]) == pytest.approx(damping, rel=1e-3)
    np.testing.assert_allclose(np.asarray(sol.value, np.float64).mean(0), mean, atol=1e-6)
    assert sol.result == optx.RESULTS.successful
    # E after every step, the start's first, never rising (a rejected step keeps E), NaN after the last
    history = np.asarray(s["history"])
    assert history.shape == (HISTORY,) and np.all(np.isnan(history[steps + 1:]))
    assert np.all(np.diff(history[: steps + 1]) <= 0) and history[0] > history[steps]
    assert history[steps] == pytest.approx(float(s["loss"]), rel=1e-6)
    # the residuals and Jacobians at the returned x are in the final state
    r, jac, e = jax.jit(linearize)(sol.value, problem)
    np.testing.assert_allclose(np.asarray(sol.state.r), np.asarray(r), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(sol.state.jac), np.asarray(jac), rtol=1e-5, atol=1e-6)
    assert float(e) == pytest.approx(float(s["loss"]), rel=1e-6)


def test_a_noiseless_solve_stops_once_e_is_within_the_targets_rounding():
    """Targets rendered from the truth without noise: the solve stops at its first step that brings
    E within `rounding_floor` (with rtol and atol 0 it went on until λ passed LAMBDA_MAX), and
    there x is the truth; the floor is far below the noisy targets' E."""
    noisy, truth = _problem(smooth=0.0)
    blank = dataclasses.replace(noisy, obs=dataclasses.replace(noisy.obs, target=jnp.zeros_like(noisy.obs.target)))
    clean = dataclasses.replace(noisy, obs=dataclasses.replace(noisy.obs, target=jax.jit(pixel_residuals)(truth, blank)))
    x0 = grid_initialise(_start(clean), clean)
    sol = optx.least_squares(lambda x, p: residuals(x, p), StructuredLM(rtol=0.0, atol=0.0), x0, args=clean,
                             options=dict(max_steps=jnp.asarray(40, jnp.int32)), max_steps=None, throw=False)
    steps = int(sol.stats["steps"])
    history = np.asarray(sol.stats["history"])[: steps + 1]
    floor = float(rounding_floor(clean))
    assert 0 < floor < 1e-9 and 2 <= steps < 15, (floor, steps, history)
    assert history[-1] <= floor < history[-2], (floor, history)
    np.testing.assert_allclose(np.asarray(sol.value)[:, [0, 1, 2, 4]], truth[:, [0, 1, 2, 4]], atol=1e-3)
    assert float(jax.jit(linearize)(x0, noisy)[2]) > 1e6 * float(rounding_floor(noisy))


def test_a_noisy_solve_stops_once_a_step_gains_less_than_its_noise():
    """Noisy targets (σ 0.01), no rtol or atol: without the noise-relative stop the solve goes on
    with refused steps at E's float32 floor; with it (the default) it stops at the first
    accepted step whose actual and predicted gains are within NOISE_RTOL · E · p / (n - p), where
    E and x are those of the longer solve to well within that tolerance and the noise."""
    problem, truth = _problem(smooth=0.0)
    x0 = grid_initialise(_start(problem), problem)
    runs = {nr: solve(x0, problem, StructuredLM(rtol=0.0, atol=0.0, noise_rtol=nr), 40) for nr in (0.0, NOISE_RTOL)}
    (x_all, all_, _, _), (x_stop, stop, _, _) = runs[0.0], runs[NOISE_RTOL]
    assert int(stop.steps) < int(all_.steps) and int(stop.accepted) == int(stop.steps), (stop.steps, all_.steps)
    p = float(np.sum(np.asarray(problem.free)))
    n = 3 * problem.num_pixels
    history = np.asarray(stop.history, np.float64)[: int(stop.steps) + 1]
    tol = NOISE_RTOL * history * p / (n - p)  # each step's tolerance, from E before it
    assert history[-2] - history[-1] <= tol[-2], (history, tol)  # the last step's gain
    assert history[-3] - history[-2] > tol[-3], (history, tol)  # the one before went on
    assert 0.0 <= float(stop.loss) - float(all_.loss) <= tol[-2]
    # the noise moves x by about 0.01 / sqrt(pixels per texel); the stop leaves far less than that
    assert np.max(np.abs(np.asarray(x_stop) - np.asarray(x_all))) < 1e-4
    assert np.max(np.abs(np.asarray(x_stop) - truth)) > 1e-3


def test_one_program_serves_every_step_budget(start):
    smooth, problem, x0 = start
    solver = StructuredLM(rtol=1e-7, atol=1e-6, noise_rtol=0.0)
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
    assert _stopped_as_before(stats30.steps, stats30.accepted, stats30.cg_iterations)
    assert float(stats30.loss) == pytest.approx(REFERENCE[smooth][0], rel=1e-5)


def test_the_runner_gives_every_tolerance_one_program():
    """The runner passes the structured solver's tolerances (rtol, atol, cg_rtol, noise_rtol) as
    arrays: solvers that differ only in them, as the quality rungs do, lower to the same program,
    and the program stops each solve at its own tolerances."""
    from pbrfit.fitting.runner import Compiler, Runner

    problem, _ = _problem()
    x0 = grid_initialise(_start(problem), problem)
    budget = jnp.asarray(30, jnp.int32)
    tight, loose = (Runner(StructuredLM(rtol, atol, cg_rtol, noise_rtol), None, Compiler({})).solver
                    for rtol, atol, cg_rtol, noise_rtol in ((1e-7, 1e-6, 1e-3, 0.0), (1e-2, 1e-3, 0.1, 1.0)))
    lowered = solve.lower(x0, problem, tight, budget)
    assert lowered.as_text() == solve.lower(x0, problem, loose, budget).as_text()
    compiled = lowered.compile()
    _, stats_tight, *_ = compiled(x0, problem, tight, budget)
    _, stats_loose, *_ = compiled(x0, problem, loose, budget)
    assert int(stats_loose.steps) < int(stats_tight.steps), (stats_loose.steps, stats_tight.steps)
    assert float(stats_tight.loss) <= float(stats_loose.loss)


@pytest.mark.parametrize("steps", [30, 3])
def test_a_solve_run_in_parts_takes_the_steps_of_one_run_bit_for_bit(start, steps):
    """A solve cut into parts of 1, 2, 3, ... steps, each going on from the last one's x and
    `LMCarry` (what a checkpoint keeps): the same x, counts, damping and losses as one run to the
    same budget, to the bit, and the same residuals and Jacobians at the end (the next part's
    first call only linearises again). A stopping test ends the solve in 30 steps (`STOPS`),
    the budget in 3."""
    _, problem, x0 = start
    solver = StructuredLM(rtol=1e-7, atol=1e-6, noise_rtol=0.0)
    budget = jnp.asarray(steps, jnp.int32)
    compiled = solve.lower(x0, problem, solver, budget, LMCarry.start()).compile()
    whole = compiled(x0, problem, solver, budget, LMCarry.start())
    x, carry, done, part, parts = x0, LMCarry.start(), 0, 1, 0
    while True:
        out = compiled(x, problem, solver, jnp.asarray(min(steps, done + part), jnp.int32), carry)
        done, parts, part = int(out[1].steps), parts + 1, part + 1
        if bool(out[1].stopped) or done >= steps:
            break
        x, carry = out[0], LMCarry.after(out[1])
    assert parts > 1 and int(whole[1].steps) == done
    assert bool(whole[1].stopped) == (steps == 30)
    for a, b in zip(jax.tree_util.tree_leaves(whole), jax.tree_util.tree_leaves(out)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_without_a_budget_optimistix_max_steps_bounds_the_solve(start):
    _, problem, x0 = start
    sol = optx.least_squares(lambda x, p: residuals(x, p), StructuredLM(rtol=1e-7, atol=1e-6, noise_rtol=0.0), x0,
                             args=problem,
                             max_steps=3, throw=False)
    assert int(sol.stats["num_steps"]) == 3 and int(sol.stats["steps"]) == 2
    assert sol.result == optx.RESULTS.nonlinear_max_steps_reached


def _capture(tmp_path):
    from _capture_fixtures import base_capture_dict, write_capture

    data = base_capture_dict()
    del data["environment"]  # point lights alone: no IBL tables to build
    return write_capture(tmp_path / "cap", data)


def test_fit_runs_a_users_optimistix_solver(tmp_path):
    seen = []
    result = pbrfit.fit(_capture(tmp_path), solver=optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6), resolution=4,
                        max_steps=4, init="prior", search=False, progress=seen.append)
    losses = [entry["loss"] for entry in seen if "loss" in entry]
    assert result.report["solver"] == "LevenbergMarquardt" and 1 <= result.report["steps"] <= 4
    assert result.report["stopping"]["rtol"] == 1e-6 and result.report["stopping"]["atol"] == 1e-6
    assert result.report["final_loss"] < 0.9 * losses[0], losses
    assert result.report["repair"] == dict(skipped="needs the structured solver")
    assert "cg_rtol" not in result.report


def test_the_command_line_names_a_solver(tmp_path):
    from pbrfit.cli.fit import fit_options
    from pbrfit.cli.main import build_parser, main

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra])).solver

    assert options() == StructuredLM() and options("--rtol", "1e-7", "--cg-rtol", "0.01") == StructuredLM(1e-7, ATOL, 0.01)
    assert options("--solver", "lm", "--atol", "1e-4") == solver_for("lm", RTOL, 1e-4)
    out = tmp_path / "fit"
    assert main(["fit", str(_capture(tmp_path)), "--out", str(out), "--solver", "lm", "--resolution", "4",
                 "--max-steps", "3", "--no-search", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["solver"] == "lm" and 1 <= report["steps"] <= 3 and np.isfinite(report["final_loss"])
