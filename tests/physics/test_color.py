"""`pbrfit.physics.color`: the sRGB curve (IEC 61966-2-1), exposure, and tone maps against numpy
re-implementations of their published formulas."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit import color


# --- sRGB ------------------------------------------------------------------------------------------
def _srgb_decode_np(x):
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _srgb_encode_np(x):
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)


def test_srgb_known_values():
    np.testing.assert_allclose(color.srgb_to_linear(0.5), 0.21404, atol=1e-5)
    np.testing.assert_allclose(color.linear_to_srgb(0.21404114), 0.5, atol=1e-5)
    np.testing.assert_allclose(color.srgb_to_linear(jnp.array([0.0, 1.0])), [0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(color.linear_to_srgb(jnp.array([0.0, 1.0])), [0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(color.linear_to_srgb(0.18), 0.46135, atol=1e-4)  # middle grey


def test_srgb_matches_the_iec_formula_and_round_trips():
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(color.srgb_to_linear(x), _srgb_decode_np(x), atol=2e-7)
    np.testing.assert_allclose(color.linear_to_srgb(x), _srgb_encode_np(x), atol=1e-6)
    np.testing.assert_allclose(color.linear_to_srgb(color.srgb_to_linear(x)), x, atol=2e-6)
    np.testing.assert_allclose(color.srgb_to_linear(color.linear_to_srgb(x)), x, atol=2e-6)


def test_host_srgb_twins_match_the_jax_curves():
    # numpy twins for file work: same formula, float32, agreeing with the jitted curves
    x = np.linspace(-0.1, 1.2, 2601).astype(np.float32)
    for host, dev, ref in ((color.srgb_to_linear_host, color.srgb_to_linear, _srgb_decode_np),
                           (color.linear_to_srgb_host, color.linear_to_srgb, _srgb_encode_np)):
        got = host(x)
        assert isinstance(got, np.ndarray) and got.dtype == np.float32
        np.testing.assert_allclose(got, np.asarray(dev(x)), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(got[x >= 0], ref(x[x >= 0]), rtol=2e-6, atol=2e-7)


def test_srgb_breakpoints_are_continuous():
    """The IEC constants make the two branches meet to ~1e-7 (they were rounded in the standard: at the
    encode breakpoint the power branch starts 3e-8 below the linear one)."""
    for fn, cut in ((color.srgb_to_linear, 0.04045), (color.linear_to_srgb, 0.0031308)):
        below, above = fn(jnp.float32(cut)), fn(jnp.float32(np.nextafter(np.float32(cut), np.float32(1))))
        assert abs(float(above) - float(below)) < 1e-6, (fn.__name__, below, above)
        lo, hi = fn(jnp.float32(cut * 0.999)), fn(jnp.float32(cut * 1.001))
        assert float(lo) < float(below) and float(above) < float(hi)
        assert float(above) >= float(below) - 1e-7


def test_srgb_gradients_finite_at_zero_and_negative():
    for fn in (color.srgb_to_linear, color.linear_to_srgb):
        for x in (0.0, -0.1, 1e-12):
            g = jax.grad(fn)(jnp.float32(x))
            assert np.isfinite(g) and g > 0, (fn.__name__, x, g)
    np.testing.assert_allclose(jax.grad(color.linear_to_srgb)(jnp.float32(0.0)), 12.92, rtol=1e-6)


# --- exposure -----------------------------------------------------------------------------------
def test_exposure_doubles_per_ev():
    x = jnp.array([0.1, 0.5, 2.0])
    np.testing.assert_allclose(color.apply_exposure(x, 1.0), 2 * x, rtol=1e-6)
    np.testing.assert_allclose(color.apply_exposure(x, -2.0), x / 4, rtol=1e-6)
    np.testing.assert_allclose(color.apply_exposure(x, 0.0), x, rtol=1e-7)
    np.testing.assert_allclose(color.apply_exposure(color.apply_exposure(x, 0.7), 0.3), 2 * x, rtol=1e-6)


# --- tone maps ------------------------------------------------------------------------------------
def _reinhard_np(x):
    return x / (1 + x)


def _narkowicz_np(x):
    return np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0, 1)


_ACES_IN = np.array([[0.59719, 0.35458, 0.04823], [0.07600, 0.90834, 0.01566], [0.02840, 0.13383, 0.83777]])
_ACES_OUT = np.array([[1.60475, -0.53108, -0.07367], [-0.10208, 1.10813, -0.00605], [-0.00327, -0.07276, 1.07602]])


def _hill_np(x):
    """S. Hill, BakingLab ACES.hlsl: ACESInputMat, RRTAndODTFit, ACESOutputMat, saturate."""
    c = x @ _ACES_IN.T
    c = (c * (c + 0.0245786) - 0.000090537) / (c * (0.983729 * c + 0.4329510) + 0.238081)
    return np.clip(c @ _ACES_OUT.T, 0, 1)


def _khronos_np(x):
    """Khronos PBR Neutral (reference GLSL, KhronosGroup/ToneMapping)."""
    start, desat = 0.8 - 0.04, 0.15
    out = np.empty_like(x)
    for i, c in enumerate(np.asarray(x, np.float64)):
        m = c.min()
        offset = m - 6.25 * m * m if m < 0.08 else 0.04
        c = c - offset
        peak = c.max()
        if peak < start:
            out[i] = c
            continue
        d = 1 - start
        new_peak = 1 - d * d / (peak + d - start)
        c = c * (new_peak / peak)
        g = 1 - 1 / (desat * (peak - new_peak) + 1)
        out[i] = c * (1 - g) + new_peak * g
    return out


_REFERENCES = {
    "reinhard": _reinhard_np,
    "aces_narkowicz": _narkowicz_np,
    "aces_hill": _hill_np,
    "khronos_neutral": _khronos_np,
}


def _colors():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (300, 3)) * rng.choice([0.05, 0.5, 1.0, 4.0, 30.0], (300, 1))
    return np.concatenate([x, np.zeros((1, 3)), np.ones((1, 3))])


@pytest.mark.parametrize("name", sorted(_REFERENCES))
def test_tonemap_matches_published_formula(name):
    x = _colors()
    np.testing.assert_allclose(color.tonemap(jnp.asarray(x, jnp.float32), name), _REFERENCES[name](x),
                               atol=2e-6, rtol=1e-5)


def test_tonemap_known_values():
    np.testing.assert_allclose(color.tonemap(jnp.full(3, 1.0), "reinhard"), 0.5, rtol=1e-7)
    np.testing.assert_allclose(color.tonemap(jnp.full(3, 1.0), "aces_narkowicz"), 2.54 / 3.16, rtol=1e-6)
    np.testing.assert_allclose(color.tonemap(jnp.zeros(3), "aces_narkowicz"), 0.0, atol=1e-7)
    assert np.all(np.asarray(color.tonemap(jnp.full(3, 100.0), "aces_narkowicz")) == 1.0)
    x = jnp.array([0.3, 0.2, 0.1])
    np.testing.assert_array_equal(color.tonemap(x, "none"), x)


@pytest.mark.parametrize("name", color.TONEMAPS)
def test_tonemap_monotone_and_bounded(name):
    s = jnp.linspace(0.0, 50.0, 2001)
    for tint in ((1.0, 1.0, 1.0), (1.0, 0.5, 0.2)):
        y = np.asarray(color.tonemap(s[:, None] * jnp.asarray(tint), name))
        assert np.all(np.isfinite(y)) and np.all(y >= 0.0)
        assert np.all(np.diff(y, axis=0) >= -1e-6), name  # channel-wise non-decreasing along a ray
        if name != "none":
            assert np.all(y <= 1.0 + 1e-6), name


@pytest.mark.parametrize("name", color.TONEMAPS)
def test_inverse_tonemap_round_trips(name):
    """inverse_tonemap(tonemap(x)) = x wherever the operator is invertible (no channel clipped to
    0 or near the top), and display values at the top come back finite."""
    x = _colors()
    y = np.asarray(color.tonemap(jnp.asarray(x, jnp.float32), name))
    back = np.asarray(color.inverse_tonemap(jnp.asarray(y), name))
    ok = np.all((y > 1e-4) & (y < 0.99), axis=1)
    assert ok.sum() > 100
    np.testing.assert_allclose(back[ok], x[ok], rtol=1e-3, atol=1e-4)
    top = np.asarray(color.inverse_tonemap(jnp.array([[1.0, 1.0, 1.0], [1.0, 0.2, 0.0]]), name))
    assert np.all(np.isfinite(top)) and np.all(top >= 0.0)
    if name != "none":
        assert np.all(top[0] > 5.0), top  # the top of the display range is far up in linear


def test_inverse_tonemap_known_values():
    np.testing.assert_allclose(color.inverse_tonemap(jnp.full(3, 0.5), "reinhard"), 1.0, rtol=1e-6)
    np.testing.assert_allclose(color.inverse_tonemap(jnp.full(3, 2.54 / 3.16), "aces_narkowicz"), 1.0, rtol=1e-5)
    x = jnp.array([0.5, 0.3, 0.1])  # Khronos PBR Neutral's identity region: x - 0.04
    np.testing.assert_allclose(color.inverse_tonemap(x - 0.04, "khronos_neutral"), x, rtol=1e-5)
    with pytest.raises(ValueError, match="tone map"):
        color.inverse_tonemap(x, "filmic")


def test_inverse_tonemap_gradients_are_finite_at_black():
    """Khronos PBR Neutral's toe inverse, sqrt(m / 6.25), has infinite slope at m = 0: a black
    channel must not send the gradient to inf or NaN (nor its neighbours' through the min)."""
    for name in color.TONEMAPS:
        for y in ([0.0, 0.0, 0.0], [0.5, 0.2, 0.0], [0.9, 0.5, 0.0]):
            g = jax.grad(lambda t: color.inverse_tonemap(t, name).sum())(jnp.asarray(y, jnp.float32))
            assert np.all(np.isfinite(np.asarray(g))), (name, y, g)
    g = jax.grad(lambda t: color.inverse_tonemap(t, "khronos_neutral")[2])(jnp.asarray([0.5, 0.2, 0.01]))
    np.testing.assert_allclose(g[2], 1.0 / (2.0 * np.sqrt(6.25 * 0.01)), rtol=1e-4)  # d sqrt(m/6.25)/dm


def test_khronos_neutral_identity_region():
    """Below the compression start (max < 0.76 after the 0.04 offset) and with min ≥ 0.08, Khronos PBR
    Neutral is x - 0.04: a base color renders as itself minus the fixed toe offset."""
    x = jnp.array([[0.5, 0.3, 0.1], [0.7, 0.7, 0.7], [0.08, 0.2, 0.79]])
    np.testing.assert_allclose(color.tonemap(x, "khronos_neutral"), x - 0.04, rtol=1e-6)
    np.testing.assert_allclose(color.tonemap(jnp.zeros(3), "khronos_neutral"), 0.0, atol=1e-7)


@pytest.mark.parametrize("name", color.TONEMAPS)
def test_tonemap_gradients_finite_at_zero(name):
    for x in (jnp.zeros(3), jnp.array([0.0, 0.5, 2.0]), jnp.full(3, 0.76)):
        g = jax.grad(lambda x: color.tonemap(x, name).sum())(x)
        assert np.all(np.isfinite(np.asarray(g))), (name, x, g)
    g = jax.grad(lambda x: color.encode(x, 0.0, name, "srgb").sum())(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g))), name


def test_derivatives_at_zero_and_at_the_clip_are_the_ones_from_inside():
    """A pixel whose radiance is exactly 0 (a metal's black channel under a flash) or exactly 1
    under sRGB keeps the derivative from inside: a clip's is half of it (a quarter through the
    Narkowicz fit's two clips), which made that channel's Gauss-Newton step and standard error
    too large. The slopes at 0: sRGB 12.92, Reinhard 1, Narkowicz 0.03 / 0.14 (Hill's fit is 0
    near black, and so is its derivative)."""
    d = lambda f, x: float(jax.grad(f)(jnp.float32(x)))  # noqa: E731
    assert d(lambda x: color.encode(x, 0.0, "none", "srgb"), 0.0) == pytest.approx(12.92)
    assert d(lambda x: color.encode(x, 0.0, "none", "srgb"), 1.0) == pytest.approx(1.055 / 2.4, rel=1e-5)
    assert d(lambda x: color.tonemap(x, "reinhard"), 0.0) == pytest.approx(1.0)
    assert d(lambda x: color.tonemap(x, "aces_narkowicz"), 0.0) == pytest.approx(0.03 / 0.14, rel=1e-5)


def test_encode_order_and_errors():
    x = jnp.array([0.1, 0.4, 3.0])
    np.testing.assert_allclose(color.encode(x, 1.0), 2 * x, rtol=1e-6)
    expect = _srgb_encode_np(np.clip(_reinhard_np(2 * np.asarray(x, np.float64)), 0, 1))
    np.testing.assert_allclose(color.encode(x, 1.0, "reinhard", "srgb"), expect, atol=1e-6)
    with pytest.raises(ValueError, match="tone map"):
        color.tonemap(x, "filmic")
    with pytest.raises(ValueError, match="color space"):
        color.encode(x, 0.0, "none", "p3")


def test_aces_fits_finite_for_huge_radiance():
    """Above `color.ACES_INPUT_MAX` both ACES fits are 1 already; the cap keeps x² and the
    derivatives' x³ inside float32 (uncapped: NaN gradient from 1e18, NaN value from 1e20)."""
    for name in ("aces_narkowicz", "aces_hill"):
        for x in ([1e20, 1.0, 0.5], [1e18, 0.0, 0.0], [3e38, 3e38, 3e38]):
            x = jnp.asarray(x, jnp.float32)
            y, jac = color.tonemap(x, name), jax.jacfwd(lambda t: color.tonemap(t, name))(x)
            assert np.all(np.isfinite(np.asarray(y))) and np.all(np.isfinite(np.asarray(jac))), (name, x)
            assert float(y[0]) == 1.0
        big = jnp.asarray([color.ACES_INPUT_MAX, 0.3, 0.0], jnp.float32)
        np.testing.assert_array_equal(color.tonemap(big, name), color.tonemap(big * jnp.asarray([10.0, 1.0, 1.0]), name))
