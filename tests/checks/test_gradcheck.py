"""`pbrfit.checks.gradcheck` (``pbrfit check-grads``): the full run passes, and a wrong derivative is caught."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import pytest

from pbrfit import brdf
from pbrfit.checks import gradcheck
from pbrfit.checks import terms as gradcheck_terms
from pbrfit.cli.main import main


@pytest.fixture(scope="module")
def results():
    """One full run (~40 s of compilation) shared by the tests of this module."""
    return gradcheck.run_checks()


def test_run_checks_passes(results):
    failed = [r for r in results if not r.passed]
    assert not failed, failed
    terms = {r.term for r in results}
    public = set(brdf.__all__) - {"MIN_ROUGHNESS", "MIN_ALPHA", "COS_MIN", "FLOORS", "evaluate_cosines"}
    assert public <= terms, public - terms
    for model in gradcheck_terms.MODEL_VARIANTS:
        assert f"evaluate_cosines[{gradcheck_terms.model_label(model)}]" in terms
    for name in ("srgb_to_linear", "linear_to_srgb", "tonemap_aces_hill", "tonemap_khronos_neutral"):
        assert name in terms
    assert {r.order for r in results} == {0, 1, 2}
    assert all(r.checked > 0 and r.tolerance == gradcheck.TOLERANCE[r.order] for r in results)
    assert all(set(r.worst_point) >= {"wrt", "autodiff", "finite_difference"} for r in results if r.order > 0)
    # every term is also swept at the ends of its inputs' domains, in float32 and in float64
    ends = {(r.term, r.dtype) for r in results if r.order == 0}
    assert ends == {(t, d) for t in terms for d in ("float32", "float64")}
    r = results[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.passed = False  # type: ignore[misc]


def _spec(term):
    return [s for s in gradcheck_terms.all_specs() if s.term == term]


def _d_ggx_with_tangent(tangent):
    """`brdf.d_ggx` whose JVP's tangent is ``tangent(primals, tangents, jvp)`` (a wrong
    derivative), ``jvp(primals, tangents)`` the true one's."""
    true_d = brdf.d_ggx

    @jax.custom_jvp
    def d_wrong(n_dot_h, alpha):
        return true_d(n_dot_h, alpha)

    @d_wrong.defjvp
    def _(primals, tangents):
        return true_d(*primals), tangent(primals, tangents, lambda p, t: jax.jvp(true_d, p, t)[1])

    return d_wrong


def test_wrong_first_derivative_is_caught(monkeypatch):
    """A custom_jvp whose derivative is 1 % off in n·h: the gradient check fails at 1st order."""
    monkeypatch.setattr(brdf, "d_ggx", _d_ggx_with_tangent(lambda p, t, jvp: jvp(p, (t[0] * 1.01, t[1]))))
    res = {r.order: r for r in gradcheck.run_checks(_spec("d_ggx"))}
    assert not res[1].passed and res[1].max_rel_error > 1e-3
    assert res[1].worst_point["wrt"] == "d/dn·h"


def test_wrong_derivative_at_low_roughness_is_caught(monkeypatch):
    """Twice the derivative below alpha 0.009 (roughness 0.095, above the fit's floor 0.045): the
    grid reaches alpha 0.005."""
    monkeypatch.setattr(brdf, "d_ggx", _d_ggx_with_tangent(
        lambda p, t, jvp: jnp.where(p[1] < 0.009, 2.0, 1.0) * jvp(p, t)))
    res = [r for r in gradcheck.run_checks(_spec("d_ggx"), ends=False) if r.order == 1]
    assert not res[0].passed and res[0].worst_point["alpha"] < 0.009, res


def test_nan_gradient_at_a_domain_end_is_caught(monkeypatch):
    """A NaN derivative at n·h = 1 (a highlight's peak), where no finite-difference stencil can
    go: the ends sweep fails, in both dtypes, and names the point."""
    monkeypatch.setattr(brdf, "d_ggx", _d_ggx_with_tangent(
        lambda p, t, jvp: jnp.where(p[0] >= 0.9999, jnp.nan, 1.0) * jvp(p, t)))
    res = gradcheck.run_checks(_spec("d_ggx"))
    assert all(r.passed for r in res if r.order > 0)
    ends = [r for r in res if r.order == 0]
    assert len(ends) == 2 and not any(r.passed for r in ends)
    assert all(r.worst_point["n·h"] >= 0.9999 and 0 < r.max_rel_error < 1 for r in ends)


def test_wrong_second_derivative_is_caught(monkeypatch):
    """A custom_jvp whose first derivative is right but not itself differentiable (stop_gradient):
    the Hessian is wrong and only the 2nd-order check sees it."""
    true_f = brdf.f_dielectric

    @jax.custom_jvp
    def f_wrong(c, ior):
        return true_f(c, ior)

    @f_wrong.defjvp
    def _(primals, tangents):
        c, ior = primals
        dc, dior = jax.grad(true_f, argnums=(0, 1))(c, ior)
        tangent = jax.lax.stop_gradient(dc) * tangents[0] + jax.lax.stop_gradient(dior) * tangents[1]
        return true_f(c, ior), tangent

    monkeypatch.setattr(brdf, "f_dielectric", f_wrong)
    res = {r.order: r for r in gradcheck.run_checks(_spec("f_dielectric"))}
    assert res[1].passed, res[1]
    assert not res[2].passed, res[2]


def test_cli_check_grads_prints_table(results, monkeypatch, capsys):
    """`pbrfit check-grads` end to end through the CLI (run_checks itself is the module fixture's run)."""
    monkeypatch.setattr(gradcheck, "run_checks", lambda: results)
    assert main(["check-grads"]) == 0
    out = capsys.readouterr().out
    assert "max rel error" in out and "d_ggx" in out and "evaluate_cosines[default]" in out
    assert "MIN_ROUGHNESS" in out and "MIN_DISTANCE" in out
    assert "check-grads: PASS" in out
    assert main(["check-grads", "--quiet"]) == 0
    quiet = capsys.readouterr().out
    assert "d_ggx" not in quiet and "check-grads: PASS" in quiet


def test_print_report_returns_false_on_failure(results, capsys):
    bad = [dataclasses.replace(results[0], passed=False, max_rel_error=1.0)] + list(results[1:])
    assert gradcheck.print_report(bad, quiet=True) is False
    out = capsys.readouterr().out
    assert "FAIL" in out and results[0].term in out


def test_ends_grid_holds_every_point_exactly_on_the_ends():
    """Where the ends' combinations are too many and are drawn, every point with each input on
    an end (a cosine at 0 or 1, roughness at its floor) is kept: only the points a float32 ulp
    off are drawn."""
    import itertools

    spec = next(s for s in gradcheck_terms.all_specs() if s.term == "evaluate_cosines[default]")
    grid = gradcheck.ends_grid(spec)
    ends = [sorted(k) or sorted({float(spec.grid[:, i].min()), float(spec.grid[:, i].max())})
            for i, k in enumerate(spec.kinks)]
    corners = set(itertools.product(*ends))
    assert len(corners) > 100 and corners <= set(map(tuple, grid.tolist()))
    assert len(grid) == gradcheck.ENDS_MAX_POINTS == len({tuple(p) for p in grid.tolist()})
