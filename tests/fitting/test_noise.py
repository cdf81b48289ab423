"""The noise level function, weighted residuals and the estimated-noise fit (`pbrfit.fitting.noise`)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit.fitting.api import fit_observations
from pbrfit.fitting.noise import MIN_BIN_COUNT, NOISE_BINS, NOISE_FLOOR, NoiseLevel, estimate_noise_level
from pbrfit.fitting.observations import neighbour_pairs, observations_from_views, texel_layout
from pbrfit.fitting.objective import Problem, linearize, pixel_residuals

from test_fit import VIEWS, _checker, _images


def _draw(level, n=60_000, seed=0, low=0.02, high=0.9):
    rng = np.random.default_rng(seed)
    v = rng.uniform(low, high, n)
    return v, rng.normal(0.0, 1.0, n) * level(v)


@pytest.mark.parametrize("level", [lambda v: 0.01 * v, lambda v: np.sqrt(1e-4 * v + 1e-6), lambda v: 0.01 + 0 * v])
def test_noise_level_recovers_the_level_function(level):
    v, r = _draw(level)
    est = estimate_noise_level(v, r)
    assert est.values.shape == (NOISE_BINS,) and np.all(np.diff(est.values) > 0)
    np.testing.assert_allclose(est.sigma, level(est.values), rtol=0.06)
    grid = np.linspace(est.values[0], est.values[-1], 50)
    np.testing.assert_allclose(est(grid), np.maximum(level(grid), NOISE_FLOOR * est.reference), rtol=0.08)
    # weights: σ_ref / σ(v), median 1 over the values it was estimated from, at most 1 / NOISE_FLOOR
    w = est.weights(v)
    assert w.dtype == np.float32 and abs(np.median(w) - 1.0) < 0.01 and w.max() <= 1.0 / NOISE_FLOOR + 1e-4


def test_noise_level_is_robust_to_a_few_gross_residuals_and_corrects_for_dof():
    v, r = _draw(lambda v: 0.01 * v)
    bad = np.random.default_rng(1).random(v.size) < 0.02
    r = np.where(bad, 0.5, r)  # a cluster the fit left in a wrong basin
    est = estimate_noise_level(v, r)
    np.testing.assert_allclose(est.sigma, 0.01 * est.values, rtol=0.12)
    twice = estimate_noise_level(v, r, dof_scale=4.0)
    np.testing.assert_allclose(twice.sigma, 2.0 * est.sigma, rtol=1e-12)
    np.testing.assert_allclose(twice.weights(v), est.weights(v), rtol=1e-6)  # the weights do not change


def test_noise_level_floor_flat_stretches_and_edge_cases():
    # noise proportional to the value vanishes at 0: the floor caps the dark values' weights
    v, r = _draw(lambda v: 0.01 * v, low=0.0, high=1.0)
    est = estimate_noise_level(v, r)
    assert est(0.0) == pytest.approx(NOISE_FLOOR * est.reference)
    assert est.weights(np.array([0.0]))[0] == pytest.approx(1.0 / NOISE_FLOOR, rel=1e-6)
    # beyond the bins the level follows the fitted shape: here c v²
    assert est.shape[2] > 0 and est.shape[0] == pytest.approx(0.0, abs=1e-9)
    assert est(5.0) == pytest.approx(0.05, rel=0.05)
    # a quantised image: many equal values share one bin, the values stay increasing
    q = np.round(v * 4) / 4
    est_q = estimate_noise_level(q, r)
    assert np.all(np.diff(est_q.values) > 0) and len(est_q.values) <= 5
    # few residuals: fewer bins, at least one
    assert len(estimate_noise_level(v[: 3 * MIN_BIN_COUNT], r[: 3 * MIN_BIN_COUNT]).values) == 3
    assert len(estimate_noise_level(v[:10], r[:10]).values) == 1
    # one bin says nothing of how the level changes with the value: a constant level, weights of
    # 1 (every one of these draws once gave a slope that round-off favoured)
    for seed in (14, 93, 107, 113, 122):
        rng = np.random.default_rng(seed)
        v1, r1 = rng.uniform(0.0, 1.0, MIN_BIN_COUNT + 100), rng.normal(0.0, 0.01, MIN_BIN_COUNT + 100)
        one = estimate_noise_level(v1, r1)
        assert len(one.values) == 1 and one.shape[1] == one.shape[2] == 0.0, one.shape
        np.testing.assert_allclose(one.weights(np.array([0.0, 0.5, 1.0, 5.0])), 1.0, rtol=1e-6)
    # a dark bin the shape fits badly (noisier than the law the rest follow): between it and the
    # next bin the level stays within theirs (the shape times the interpolated ratio overshot both
    # by 2.5 times here)
    rng = np.random.default_rng(2)
    vd = np.concatenate([rng.uniform(0.0, 1e-3, 2000), rng.uniform(0.01, 1.0, 30000)])
    dark = estimate_noise_level(vd, rng.normal(0.0, 1.0, vd.size) * np.where(vd < 1e-3, 2e-3, 0.01 * vd))
    gap = np.linspace(dark.values[0], dark.values[1], 50)
    assert np.all(dark(gap) <= max(dark.sigma[:2]) * (1 + 1e-9)), (dark(gap).max(), dark.sigma[:2])
    # a value that is not a number (a render's NaN) gets weight 1
    assert est.weights(np.array([np.nan]))[0] == 1.0
    # an exact fit: no level to weigh by, every weight 1
    exact = estimate_noise_level(v, np.zeros_like(v))
    np.testing.assert_array_equal(exact.weights(v), np.ones(v.shape, np.float32))
    # non-finite components are left out; nothing finite or mismatched sizes are errors
    est_nan = estimate_noise_level(np.append(v, np.nan), np.append(r, 1.0))
    np.testing.assert_allclose(est_nan.sigma, est.sigma)
    with pytest.raises(ValueError, match="same size"):
        estimate_noise_level(v, r[:-1])
    with pytest.raises(ValueError, match="no finite residual"):
        estimate_noise_level([np.nan], [0.1])
    d = est.describe()
    assert set(d) == {"values", "sigma", "shape", "reference_sigma", "floor"} and len(d["sigma"]) == len(d["values"])
    # without a shape the bins' variances are interpolated, and held beyond them
    plain = NoiseLevel(np.array([0.0, 1.0]), np.array([1.0, 2.0]), np.zeros(3), 1.5)
    assert plain(0.5) == pytest.approx(np.sqrt(2.5)) and plain(3.0) == pytest.approx(2.0)


def test_residual_weights_scale_the_residuals_and_their_jacobians():
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    layout = texel_layout(obs, (8, 8))
    pairs = neighbour_pairs((8, 8))
    problem = Problem(obs, layout.index, layout.weight, jnp.ones((64, 5)), jnp.asarray(pairs),
                      jnp.zeros(len(pairs)), jnp.float32(0.0), jnp.float32(0.05))
    w = np.random.default_rng(0).uniform(0.2, 3.0, (obs.num_rows, 3)).astype(np.float32)
    weighted = dataclasses.replace(problem, obs=dataclasses.replace(obs, residual_weight=jnp.asarray(w)))
    x = jnp.full((64, 5), 0.4)
    r1, j1, _ = jax.jit(linearize)(x, problem)
    rw, jw, loss = jax.jit(linearize)(x, weighted)
    np.testing.assert_allclose(np.asarray(rw), w * np.asarray(r1), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(np.asarray(jw), w[:, :, None] * np.asarray(j1), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(float(loss), 0.5 * np.sum((w * np.asarray(r1)) ** 2), rtol=1e-5)
    # two programs of the same residuals round alike only up to float32's last bits (an AVX2 host's
    # differ from an AVX-512 host's by up to 3e-7 here)
    np.testing.assert_allclose(np.asarray(jax.jit(pixel_residuals)(x, weighted)), np.asarray(rw), rtol=1e-5, atol=1e-6)
    # the robust loss acts on the weighted residual
    huber = dataclasses.replace(weighted, loss="huber")
    np.testing.assert_allclose(np.asarray(jax.jit(pixel_residuals)(x, huber)),
                               np.asarray(pbrfit_robust(np.asarray(rw), 0.05)), rtol=1e-5, atol=1e-7)
    # and so does the Cauchy loss; residuals on both sides of the scale c, where the loss bends
    a = np.abs(np.asarray(rw))
    assert np.mean(a > 0.05) > 0.1 and np.mean((a > 0.005) & (a < 0.05)) > 0.1
    cauchy = dataclasses.replace(weighted, loss="cauchy")
    np.testing.assert_allclose(np.asarray(jax.jit(pixel_residuals)(x, cauchy)),
                               cauchy_residual(np.asarray(rw, np.float64), 0.05), rtol=1e-5, atol=1e-7)


def pbrfit_robust(r, c):
    """Huber's residual transform, written out: r for |r| <= c, else sign(r) sqrt(2 c |r| - c²)."""
    a = np.abs(r)
    return np.where(a <= c, r, np.sign(r) * np.sqrt(np.maximum(2 * c * a - c * c, 0.0)))


def cauchy_residual(r, c):
    """The Cauchy loss's residual transform, written out: ρ(s) = c² log(1 + s / c²) for s = r²,
    and the residual whose square is ρ(r²), sign(r) c sqrt(log(1 + r² / c²))."""
    return np.sign(r) * c * np.sqrt(np.log1p(r * r / (c * c)))


@pytest.fixture(scope="module")
def relative_noise_obs():
    """The checker scene with noise of 5% of each value."""
    rng = np.random.default_rng(3)
    images = [i * (1.0 + 0.05 * rng.standard_normal(i.shape)).astype(np.float32) for i in _images(VIEWS, _checker())]
    return observations_from_views(VIEWS, images)


def test_estimated_noise_level_fit_weighs_by_the_level(relative_noise_obs):
    obs = relative_noise_obs
    plain = fit_observations(obs, resolution=8, max_steps=20)
    steps = []
    est = fit_observations(obs, resolution=8, max_steps=20, noise_level="estimated", progress=steps.append)
    # the second fit's steps say so, the first's do not (though it reuses the first's executables)
    tagged = [bool(h.get("weighted")) for h in steps]
    assert 0 < tagged.index(True) and all(tagged[tagged.index(True):]), tagged
    # the second fit starts in the first's repaired basins: it runs no repair of its own, and
    # reports the first's
    assert not any(h.get("repair") for h in steps if h.get("weighted"))
    assert any(h.get("repair") for h in steps if not h.get("weighted"))
    assert est.report["repair"] == plain.report["repair"]
    assert plain.report["noise_level"] == dict(mode="uniform")
    level = est.report["noise_level"]
    assert level["mode"] == "estimated" and level["floor"] == NOISE_FLOOR
    values, sigma = np.array(level["values"]), np.array(level["sigma"])
    # noise of 5% of the value: the level grows in proportion
    np.testing.assert_allclose(sigma / values, 0.05, rtol=0.3)
    assert sigma[-1] / sigma[0] > 0.7 * values[-1] / values[0] > 1.4
    # the second fit is the first's steps and its own; its loss is of the weighted residuals, whose σ
    # is the reference level (the weights' median is 1), while its renders and PSNR are the images'
    first = level["first_fit"]
    assert est.report["steps"] > first["steps"] == plain.report["steps"]
    assert first["final_loss"] == pytest.approx(plain.report["final_loss"], rel=1e-6)
    assert est.report["residual_sigma"] == pytest.approx(level["reference_sigma"], rel=0.15)
    np.testing.assert_allclose(est.report["psnr"], plain.report["psnr"], atol=1.0)
    for img, tgt, msk in zip(est.images, est.targets, est.masks):
        assert np.sqrt(np.mean((img - tgt)[msk] ** 2)) < 0.05
    # the weights make the bright pixels' residuals count less: the bright checker's base colour
    # is known less well relative to its value than under one σ̂ for all, the dark one's better
    ratio = np.asarray(est.uncertainty)[..., :3] / np.asarray(plain.uncertainty)[..., :3]
    base = np.asarray(_checker().base_color)
    assert np.median(ratio[base > 0.55]) > np.median(ratio[base < 0.25])


def test_fit_observations_rejects_an_unknown_noise_level(relative_noise_obs):
    with pytest.raises(ValueError, match="noise_level must be one of uniform, estimated"):
        fit_observations(relative_noise_obs, resolution=8, noise_level="poisson")
