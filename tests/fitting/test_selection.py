"""The uniform check's statistics (`pbrfit.fitting.stages.selection`), against their definitions."""

import numpy as np

from pbrfit.fitting.stages.selection import (aic_statistic, newton_value, prefers_uniform, texel_precisions, wald_statistic,
                              weighted_value)


def _spd_blocks(t=6, k=5, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(t, 8, k))
    return np.einsum("tri,trj->tij", a, a) + 0.1 * np.eye(k)


def test_texel_precisions_are_the_schur_complements_over_the_fitted_channels():
    blocks = _spd_blocks()
    channels = np.array([1, 1, 1, 1, 0], bool)  # roughness held: it does not enter the complement
    seen = np.array([1, 1, 1, 0, 1, 1], bool)
    s = texel_precisions(blocks, channels, seen)[:, 3]
    others = [0, 1, 2]
    for t in range(len(blocks)):
        d = blocks[t]
        schur = d[3, 3] - d[3, others] @ np.linalg.solve(d[np.ix_(others, others)], d[others, 3])
        np.testing.assert_allclose(s[t], schur if seen[t] else 0.0, rtol=1e-6)  # float32 errors
    # with every channel free the complement is smaller (more to trade against), never larger
    assert np.all(texel_precisions(blocks, np.ones(5, bool), seen)[seen, 3] < s[seen])


def test_texel_precision_of_a_channel_no_pixel_constrains_is_zero():
    blocks = _spd_blocks(t=3)
    blocks[0, 4, :] = blocks[0, :, 4] = 0.0  # texel 0: roughness moves no pixel
    # texel 1: roughness moves the pixels exactly as base R does (a singular block whose row for
    # roughness is not zero): the images cannot tell the two apart, so neither is constrained
    rng = np.random.default_rng(1)
    a = rng.normal(size=(8, 5))
    a[:, 4] = a[:, 0]
    blocks[1] = a.T @ a
    s = texel_precisions(blocks, np.ones(5, bool), np.ones(3, bool))[:, 4]
    assert s[0] == 0.0 and s[1] == 0.0 and s[2] > 0.0


def test_weighted_value_wald_and_newton():
    values = np.array([0.0, 0.2, 0.4])
    w = np.array([1.0, 1.0, 2.0])
    assert weighted_value(values, w, 0.0, 1.0) == (0.2 + 0.8) / 4.0
    assert weighted_value(values - 1.0, w, 0.0, 1.0) == 0.0  # projected onto the bounds
    assert weighted_value(values, np.zeros(3), 0.0, 1.0) == np.mean(values)
    np.testing.assert_allclose(wald_statistic(values, w, 0.25, 0.01), (0.0625 + 0.0025 + 2 * 0.0225) / 0.01)
    assert newton_value(0.5, 2.0, 4.0, 0.0, 1.0) == 0.0  # 0.5 - 2/4 = 0
    assert newton_value(0.1, 2.0, 4.0, 0.0, 1.0) == 0.0  # projected
    assert newton_value(0.1, -2.0, 4.0, 0.0, 1.0) == 0.6
    assert newton_value(0.3, 1.0, 0.0, 0.0, 1.0) == 0.3  # no curvature: no step


def test_aic_threshold():
    # Δ = 2 (E_u - E_m) / σ² against 2 (T - 1)
    assert aic_statistic(1.5, 1.0, 0.01) == 100.0
    assert prefers_uniform(100.0, 51) and not prefers_uniform(100.0 + 1e-9, 51)
    assert prefers_uniform(-3.0, 2)  # a uniform fit that ends lower is kept
