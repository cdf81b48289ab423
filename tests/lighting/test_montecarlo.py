"""Monte Carlo machinery: sampling distributions (chi² against their densities) and the reference
integrator's convergence (1/√N to a known answer) and consistency."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from pbrfit.lighting.environment import Environment, procedural_sky, texel_directions, texel_solid_angles
from pbrfit.lighting.brdf_lut import specular_albedo
from pbrfit.physics.model import Model
from pbrfit.lighting.montecarlo import environment_pdf, environment_sampler, monte_carlo_radiance, sample_environment
from pbrfit.lighting.sampling import ggx_vndf_pdf, hammersley, sample_ggx_ndf, sample_ggx_vndf

P = 256
MC_SAMPLES = 64


def _chi2_pvalue(counts, expected):
    """Pearson chi² with bins of expected count < 5 pooled into one (Mitsuba's chi2 test does the same)."""
    counts, expected = np.asarray(counts, float).ravel(), np.asarray(expected, float).ravel()
    small = expected < 5
    obs = np.append(counts[~small], counts[small].sum())
    exp = np.append(expected[~small], expected[small].sum())
    keep = exp > 0
    chi2 = ((obs[keep] - exp[keep]) ** 2 / exp[keep]).sum()
    return stats.chi2.sf(chi2, keep.sum() - 1)


def _theta_edges(nt):
    """Polar bin edges crowded towards the pole (θ_k = π/2 (k/nt)^2), where sharp lobes live."""
    return np.pi / 2 * (np.arange(nt + 1) / nt) ** 2


def _hemisphere_bins(pdf, nt=12, nphi=16, sub=24):
    """Probability of each (θ, φ) bin of the upper hemisphere under ``pdf(l)`` (solid angle)."""
    e = _theta_edges(nt)
    th = (e[:-1, None] + (np.arange(sub) + 0.5)[None, :] / sub * np.diff(e)[:, None]).ravel()
    dth = np.repeat(np.diff(e) / sub, sub)
    ph = (np.arange(nphi * sub) + 0.5) / (nphi * sub) * 2 * np.pi
    t, p = np.meshgrid(th, ph, indexing="ij")
    l = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    w = pdf(l) * (np.sin(t) * dth[:, None]) * (2 * np.pi / (nphi * sub))
    return w.reshape(nt, sub, nphi, sub).sum((1, 3))


def _bin_counts(l, nt=12, nphi=16):
    up = l[:, 2] > 0
    it = np.clip(np.searchsorted(_theta_edges(nt), np.arccos(np.clip(l[up, 2], 0, 1))) - 1, 0, nt - 1)
    ip = np.minimum((np.mod(np.arctan2(l[up, 1], l[up, 0]), 2 * np.pi) / (2 * np.pi) * nphi).astype(int), nphi - 1)
    counts = np.zeros((nt, nphi))
    np.add.at(counts, (it, ip), 1)
    return counts, (~up).sum()


def _ggx_d(nh, a):
    return a * a / (np.pi * (nh * nh * (a * a - 1) + 1) ** 2)


def test_hammersley_points():
    u = hammersley(8)
    assert u.shape == (8, 2) and np.all((u >= 0) & (u < 1))
    np.testing.assert_allclose(u[:, 1], [0, 0.5, 0.25, 0.75, 0.125, 0.625, 0.375, 0.875])


@pytest.mark.parametrize("alpha", [0.1, 0.5])
def test_chi2_ggx_ndf_sampling(alpha):
    """Half vectors from `sample_ggx_ndf` follow D(h) (n·h) (the prefilter's sampler)."""
    m = 40000
    u = jax.random.uniform(jax.random.PRNGKey(0), (m, 2))
    h = np.asarray(sample_ggx_ndf(u, alpha), np.float64)
    counts, below = _bin_counts(h)
    assert below == 0
    expected = m * _hemisphere_bins(lambda x: _ggx_d(x[..., 2], alpha) * x[..., 2])
    assert _chi2_pvalue(counts, expected) > 1e-3


@pytest.mark.parametrize("nv,alpha", [(0.6, 0.3), (0.15, 0.6), (1.0, 0.2)])
def test_chi2_ggx_visible_normal_sampling(nv, alpha):
    """Reflected directions from `sample_ggx_vndf` follow `ggx_vndf_pdf` = G1(v) D(h) / (4 n·v)."""
    m = 40000
    v = np.array([np.sqrt(1 - nv * nv), 0.0, nv])
    u = jax.random.uniform(jax.random.PRNGKey(1), (m, 2))
    h = np.asarray(sample_ggx_vndf(jnp.asarray(np.tile(v, (m, 1)), jnp.float32), jnp.full((m,), alpha), u), np.float64)
    l = 2 * (h @ v)[:, None] * h - v
    counts, below = _bin_counts(l)

    def pdf(l):
        hh = l + v
        hh = hh / np.linalg.norm(hh, axis=-1, keepdims=True)
        return np.asarray(ggx_vndf_pdf(jnp.asarray(nv), jnp.asarray(hh[..., 2]), alpha), np.float64)

    expected = m * _hemisphere_bins(pdf)
    p = _chi2_pvalue(np.append(counts, below), np.append(expected, m - expected.sum()))
    assert p > 1e-3


def test_environment_sampling_matches_its_density():
    env = procedural_sky(16, sun_radius_deg=8.0)
    smp = environment_sampler(env.radiance)
    omega = texel_solid_angles(16, 32)
    assert (np.asarray(smp.texel_pdf) * omega).sum() == pytest.approx(1.0, rel=1e-5)
    m = 50000
    d, pdf = sample_environment(smp, jax.random.uniform(jax.random.PRNGKey(2), (m, 3)))
    np.testing.assert_allclose(pdf, environment_pdf(smp, d), rtol=1e-6)    # sampled and evaluated agree
    d = np.asarray(d)
    i = np.minimum((np.arccos(np.clip(d[:, 1], -1, 1)) / np.pi * 16).astype(int), 15)
    j = np.minimum((np.mod(np.arctan2(d[:, 0], -d[:, 2]) / (2 * np.pi) + 0.5, 1.0) * 32).astype(int), 31)
    counts = np.zeros((16, 32))
    np.add.at(counts, (i, j), 1)
    assert _chi2_pvalue(counts, m * np.asarray(smp.texel_pdf) * omega) > 1e-3


@pytest.fixture(scope="module")
def metal_case():
    """A constant environment on a white metal: L_o = L (scale + bias), known from `specular_albedo`."""
    env = Environment(jnp.ones((16, 32, 3), jnp.float32))
    nv = 0.5
    n = jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (P, 1))
    v = jnp.tile(jnp.array([[math.sqrt(1 - nv * nv), 0.0, nv]]), (P, 1))
    args = (env, n, v, jnp.ones((P, 3)), jnp.ones((P, 1)), jnp.full((P, 1), 0.4))
    exact = float(np.asarray(specular_albedo(nv, 0.4, 8192)).sum())
    return args, exact


def test_monte_carlo_converges_at_one_over_sqrt_n(metal_case):
    args, exact = metal_case
    runs = np.stack([np.asarray(monte_carlo_radiance(*args, Model(), MC_SAMPLES, jax.random.PRNGKey(k)))[:, 0]
                     for k in range(16)])                          # 16 × 64 samples, P independent points
    ns, rmse = [], []
    for k in (1, 4, 16):
        est = runs[:k].mean(0)
        ns.append(MC_SAMPLES * k)
        rmse.append(np.sqrt(np.mean((est - exact) ** 2)))
    slope = np.polyfit(np.log(ns), np.log(rmse), 1)[0]
    assert -0.62 < slope < -0.38, (ns, rmse)
    assert abs(runs.mean() - exact) < 4 * runs.std() / math.sqrt(runs.size)        # unbiased


def test_monte_carlo_linear_environment_lambert():
    """Diffuse-only white Lambert under L = 1 + ω_y: L_o = 1 + (2/3) n_y."""
    d = texel_directions(64, 128)
    env = Environment(jnp.asarray(np.repeat(1.0 + d[..., 1:2], 3, -1), jnp.float32))
    rng = np.random.default_rng(0)
    n = rng.normal(size=(P, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    v = n                                                                  # n·v = 1
    out = monte_carlo_radiance(env, jnp.asarray(n, jnp.float32), jnp.asarray(v, jnp.float32), jnp.ones((P, 3)),
                               jnp.zeros((P, 1)), jnp.full((P, 1), 0.5), Model(specular=False), MC_SAMPLES)
    err = np.asarray(out)[:, 0] - (1 + 2 / 3 * n[:, 1])
    assert abs(err.mean()) < 4 * err.std() / math.sqrt(P) + 1e-3
    assert err.std() < 0.2


def test_monte_carlo_is_the_same_at_any_batch(metal_case):
    """The estimate depends on the key and sample count only, not on how the loop is batched
    (also guards the CPU miscompilation of jax-ml/jax#39103 on large batches)."""
    from pbrfit.lighting import montecarlo

    args, _ = metal_case
    env, n, v, b, m, r = args
    a = monte_carlo_radiance(env, n, v, b, m, r, Model(), MC_SAMPLES, jax.random.PRNGKey(7))   # batch 64
    c = montecarlo._mc(env, n, v, b, m, r, None, Model(), MC_SAMPLES, 4, jax.random.PRNGKey(7))
    np.testing.assert_allclose(a, c, rtol=2e-5)


def test_monte_carlo_gradients_are_finite(metal_case):
    args, _ = metal_case
    env, n, v, b, m, r = args

    def loss(rad, b, r):
        return monte_carlo_radiance(Environment(rad), n, v, b, m, r, Model(), MC_SAMPLES).sum()

    g = jax.grad(loss, argnums=(0, 1, 2))(env.radiance, b, jnp.zeros_like(r))
    assert all(np.all(np.isfinite(x)) for x in g) and float(jnp.abs(g[0]).sum()) > 0
