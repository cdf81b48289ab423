"""Environment maps and the split sum: orientation, resampling, irradiance, prefiltering, LUT, shading.

Physics checks: a constant environment is reproduced exactly by every table and the split sum
matches the Monte Carlo reference there; SH9 irradiance is exact for a linear environment and
within Ramamoorthi & Hanrahan's bound otherwise; the LUT matches a brute-force quadrature.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit import brdf
from pbrfit.lighting.environment import (Environment, dot3, environment_lookup, load_environment, procedural_sky,
                                resample_equirect, texel_directions, texel_solid_angles)
from pbrfit.errors import CaptureError
from pbrfit.lighting.brdf_lut import brdf_lut, lookup_brdf_lut, specular_albedo
from pbrfit.lighting.ibl import (IBLSettings, build_ibl, irradiance_lookup, irradiance_map, prefiltered_lookup, sh9_coefficients,
                        sh9_irradiance, shade_ibl)
from pbrfit.physics.model import Model
from pbrfit.lighting.montecarlo import monte_carlo_radiance

SMALL = IBLSettings(lut_size=32, lut_samples=512, prefilter_levels=5, prefilter_resolution=16,
                    prefilter_samples=32, irradiance_resolution=8, env_resolution=32)
P = 256                      # points per Monte Carlo call: one compiled shape for the whole module
RUNS = 16                    # independent Monte Carlo runs per comparison (for the noise estimate)
MC_SAMPLES = 64              # per run; the same static value in every test (one compilation per model)


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _linear_env(a=1.0, b=0.5, h=64):
    """L(ω) = a + b ω_y in every channel: its irradiance is E/π = a + (2/3) b n_y exactly."""
    d = texel_directions(h, 2 * h)
    return Environment(jnp.asarray(np.repeat(a + b * d[..., 1:2], 3, -1), jnp.float32))


# --- orientation and lookup ------------------------------------------------------------------

def _coded_env(h=8, w=16):
    """Each texel holds (u, v, 0) of its centre, so a lookup says where it read."""
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
    return np.stack([u, v, np.zeros_like(u)], -1).astype(np.float32)


@pytest.mark.parametrize("up", ["+y", "+z"])
def test_orientation_follows_the_capture_format(up):
    env = Environment(jnp.asarray(_coded_env()), world_up=up)
    upv = np.array([0, 1.0, 0]) if up == "+y" else np.array([0, 0, 1.0])
    fwd = np.array([0, 0, -1.0]) if up == "+y" else np.array([0, 1.0, 0])   # image centre
    right = np.array([1.0, 0, 0])                                          # u = 0.75
    out = np.asarray(environment_lookup(env, jnp.asarray(np.stack([upv, fwd, right]), jnp.float32)))
    assert out[0, 1] == pytest.approx(1 / 16)                 # top row (clamped texel centre)
    assert out[1, :2] == pytest.approx([0.5, 0.5], abs=1e-6)
    assert out[2, :2] == pytest.approx([0.75, 0.5], abs=1e-6)


def test_rotation_turns_counter_clockwise_seen_from_above():
    env = Environment(jnp.asarray(_coded_env()), rotation_deg=90.0)
    # Turned 90° CCW seen from +y, what was at +x (u = 0.75) now lies towards -z.
    out = np.asarray(environment_lookup(env, jnp.array([[0.0, 0.0, -1.0]])))
    assert out[0, :2] == pytest.approx([0.75, 0.5], abs=1e-6)


def test_z_up_with_rotation_minus_90_is_blenders_world_mapping():
    # Blender's equirectangular world texture: u = 0.5 - atan2(y, x) / 2π, v = acos(z) / π
    env = Environment(jnp.asarray(_coded_env(16, 32)), world_up="+z", rotation_deg=-90.0)
    dirs = _unit(np.random.default_rng(3).normal(size=(200, 3)))
    u = (0.5 - np.arctan2(dirs[:, 1], dirs[:, 0]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(dirs[:, 2], -1, 1)) / np.pi
    inner = (u > 1 / 32) & (u < 31 / 32) & (v > 1 / 16) & (v < 15 / 16)  # bilinear reads of the coded
    out = np.asarray(environment_lookup(env, jnp.asarray(dirs[inner], jnp.float32)))  # map return (u, v)
    np.testing.assert_allclose(out[:, 0], u[inner], atol=1e-5)
    np.testing.assert_allclose(out[:, 1], v[inner], atol=1e-5)


def test_lookup_is_seamless_across_the_azimuth_wrap():
    rng = np.random.default_rng(0)
    env = Environment(jnp.asarray(rng.random((8, 16, 3)), jnp.float32))
    eps = 1e-4
    d = jnp.asarray(_unit(np.array([[-eps, 0.3, 1.0], [eps, 0.3, 1.0]])), jnp.float32)   # u just below 1, above 0
    a, b = np.asarray(environment_lookup(env, d))
    assert np.abs(a - b).max() < 1e-3
    # ...and at the seam the value is the mean of the first and last columns (bilinear wrap).
    row = np.asarray(environment_lookup(env, jnp.array([[0.0, 0.0, 1.0]])))[0]
    rad = np.asarray(env.radiance)
    np.testing.assert_allclose(row, 0.25 * (rad[3, 0] + rad[3, -1] + rad[4, 0] + rad[4, -1]), atol=1e-6)


def test_lookups_meet_at_the_poles():
    """Near a pole every azimuth reads towards one value, the first (last) row's mean: the map
    is continuous there, as the sphere is, and the pole itself reads that mean."""
    rng = np.random.default_rng(1)
    env = Environment(jnp.asarray(rng.random((8, 16, 3)), jnp.float32))
    rad = np.asarray(env.radiance)
    for y, row in ((1.0, 0), (-1.0, -1)):
        phi = np.linspace(0, 2 * np.pi, 7, endpoint=False)
        s = 1e-4
        near = np.stack([s * np.sin(phi), np.full_like(phi, y), -s * np.cos(phi)], -1)
        out = np.asarray(environment_lookup(env, jnp.asarray(_unit(near), jnp.float32)))
        np.testing.assert_allclose(out, np.broadcast_to(rad[row].mean(0), out.shape), atol=1e-3)
        pole = np.asarray(environment_lookup(env, jnp.array([[0.0, y, 0.0]])))[0]
        np.testing.assert_allclose(pole, rad[row].mean(0), rtol=1e-5)


def test_irradiance_straight_up_under_an_asymmetric_sky():
    """A floor's normal looks at the pole of a y-up map. The default tables' E/π there agrees
    with brute-force quadrature over the source texels to 0.5% (0.1%; clamping to the first
    row, which reads one azimuth of a ring 2.8° from the pole, was 1.7% off on this sky)."""
    sky = procedural_sky(64, sun_elevation_deg=60.0)
    rad = np.asarray(sky.radiance, np.float64)
    h, w = rad.shape[:2]
    d = texel_directions(h, w).reshape(-1, 3)
    omega = np.broadcast_to(texel_solid_angles(h, w), (h, w)).reshape(-1)
    tables = build_ibl(sky)
    for n in (np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.0])):
        exact = (rad.reshape(-1, 3) * (np.clip(d @ n, 0, None) * omega)[:, None]).sum(0) / np.pi
        got = np.asarray(irradiance_lookup(tables, jnp.asarray(n[None], jnp.float32)))[0]
        np.testing.assert_allclose(got, exact, rtol=5e-3)


def test_load_environment(tmp_path):
    import OpenImageIO as oiio

    pix = np.random.default_rng(1).random((4, 8, 1)).astype(np.float32)
    path = tmp_path / "env.exr"
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(8, 4, 1, "float"))
    out.write_image(pix)
    out.close()
    env = load_environment(path, world_up="+z", intensity=2.0, rotation_deg=30.0)
    assert env.radiance.shape == (4, 8, 3) and env.world_up == "+z" and env.rotation_deg == 30.0
    np.testing.assert_allclose(np.asarray(env.radiance), 2.0 * np.repeat(pix, 3, -1), rtol=1e-6)
    with pytest.raises(CaptureError, match="not found"):
        load_environment(tmp_path / "missing.hdr")
    assert float(load_environment(path, intensity=np.float32(2.0)).radiance[0, 0, 0]) == pytest.approx(2.0 * pix[0, 0, 0])
    for kwargs, match in ((dict(rotation_deg=float("nan")), "rotation_deg must be a finite number, got nan"),
                          (dict(intensity=True), "intensity must be a finite number >= 0, got True")):
        with pytest.raises(CaptureError, match=match):
            load_environment(path, **kwargs)
    (tmp_path / "junk.exr").write_text("not an image")
    with pytest.raises(CaptureError, match="junk.exr"):
        load_environment(tmp_path / "junk.exr")
    pix[2, 5] = np.nan
    out = oiio.ImageOutput.create(str(tmp_path / "nan.exr"))
    out.open(str(tmp_path / "nan.exr"), oiio.ImageSpec(8, 4, 1, "float"))
    out.write_image(pix)
    out.close()
    with pytest.raises(CaptureError, match=r"nan.exr: 1 environment pixels with NaN or inf values \(first at row 2, column 5\)"):
        load_environment(tmp_path / "nan.exr")
    # a cropped OpenEXR is its display window, 0 outside the data window; overscan is cut
    crop = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3) + 1.0
    for name, origin, display, inside in (("crop", (4, 1), (0, 0, 8, 4), (slice(1, 3), slice(4, 7))),
                                          ("overscan", (-1, -1), (0, 0, 2, 1), (slice(0, 1), slice(0, 2)))):
        spec = oiio.ImageSpec(3, 2, 3, "float")
        spec.x, spec.y = origin
        spec.full_x, spec.full_y, spec.full_width, spec.full_height = display
        out = oiio.ImageOutput.create(str(tmp_path / f"{name}.exr"))
        assert out.open(str(tmp_path / f"{name}.exr"), spec) and out.write_image(crop)
        out.close()
        radiance = np.asarray(load_environment(tmp_path / f"{name}.exr").radiance)
        assert radiance.shape == (display[3], display[2], 3)
        expected = np.zeros_like(radiance)
        expected[inside] = crop if name == "crop" else crop[1:2, 1:3]
        np.testing.assert_array_equal(radiance, expected)


def test_environment_not_two_to_one_is_read_with_a_warning(tmp_path):
    """A 1:1 image (a mirror-ball probe's shape) is read as lat-long, as the spec says, with one
    warning per file; 2:1 and odd widths one pixel off are read silently."""
    import warnings

    from pbrfit.lighting.environment import EnvironmentWarning
    from pbrfit.io.images import write_image

    for name, shape in (("ok", (4, 8)), ("odd", (5, 9)), ("square", (6, 6))):
        write_image(tmp_path / f"{name}.exr", np.ones(shape + (3,), np.float32), "float")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for name in ("ok", "odd", "square", "square"):
            assert load_environment(tmp_path / f"{name}.exr").radiance.shape[:2] == {
                "ok": (4, 8), "odd": (5, 9), "square": (6, 6)}[name]
    said = [str(w.message) for w in caught if issubclass(w.category, EnvironmentWarning)]
    assert len(said) == 1 and "square.exr: environment is 6 x 6, not 2:1" in said[0]


def test_resampling_preserves_the_sphere_integral():
    img = jnp.asarray(np.random.default_rng(2).random((16, 32, 3)), jnp.float32)
    total = (np.asarray(img) * texel_solid_angles(16, 32)[..., None]).sum((0, 1))
    for h, w in [(8, 16), (5, 7), (1, 2)]:
        out = np.asarray(resample_equirect(img, h, w))
        np.testing.assert_allclose((out * texel_solid_angles(h, w)[..., None]).sum((0, 1)), total, rtol=1e-5)


# --- irradiance ----------------------------------------------------------------------------------

def test_irradiance_of_a_linear_environment_is_exact():
    env = _linear_env()
    n = texel_directions(6, 12).reshape(-1, 3)
    expect = 1.0 + (2.0 / 3.0) * 0.5 * n[:, 1]
    sh = np.asarray(sh9_irradiance(sh9_coefficients(env.radiance), jnp.asarray(n, jnp.float32)))[:, 0]
    mp = np.asarray(irradiance_map(env.radiance, 6)).reshape(-1, 3)[:, 0]
    np.testing.assert_allclose(sh, expect, atol=2e-3)
    np.testing.assert_allclose(mp, expect, atol=2e-3)


def test_sh9_irradiance_within_the_known_error_bound():
    """R&H 2001: order-2 SH approximates the clamped cosine A(t) = max(t, 0) by
    A2(t) = 1/4 + t/2 + 5/16 (3t^2 - 1)/2, max |A - A2| = 3/32 (at t = 0); so
    |E - E_sh|/π <= 3/32 ∫ L dω / π."""
    env = procedural_sky(32, sun_radius_deg=6.0)
    rad = env.radiance
    n = texel_directions(8, 16).reshape(-1, 3)
    brute = np.asarray(irradiance_map(rad, 8)).reshape(-1, 3)
    sh = np.asarray(sh9_irradiance(sh9_coefficients(rad), jnp.asarray(n, jnp.float32)))
    bound = 3 / 32 * (np.asarray(rad) * texel_solid_angles(32, 64)[..., None]).sum((0, 1)) / math.pi
    err = np.abs(sh - brute).max(0)
    assert np.all(err <= bound)
    assert np.all(err > 0.05 * bound)              # a sun is not band-limited: the error is real
    # (the bound 3/32 is 1/4 - 5/32, attained at t = 0)


@pytest.fixture(scope="module")
def constant_tables():
    env = Environment(jnp.full((16, 32, 3), 1.5, jnp.float32))
    return env, build_ibl(env, SMALL)


@pytest.fixture(scope="module")
def sky_tables():
    env = procedural_sky(16, sun_radius_deg=10.0)
    return env, build_ibl(env, SMALL)


def test_constant_environment_tables(constant_tables):
    env, sh = constant_tables
    n = jnp.asarray(_unit(np.random.default_rng(3).normal(size=(50, 3))), jnp.float32)
    from pbrfit.lighting.ibl import irradiance_lookup
    np.testing.assert_allclose(irradiance_lookup(sh, n), 1.5, rtol=2e-3)
    np.testing.assert_allclose(irradiance_map(env.radiance, 8), 1.5, rtol=1e-5)
    for k, (h, w) in enumerate(sh.level_shapes):
        np.testing.assert_allclose(sh.prefiltered[k, :h, :w], 1.5, rtol=1e-5)
    r = jnp.linspace(0, 1, 50)
    np.testing.assert_allclose(prefiltered_lookup(sh, n, r), 1.5, rtol=1e-5)


# --- the BRDF LUT ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def lut():
    return np.asarray(brdf_lut(32, 512))


def test_lut_layout_and_limits(lut):
    assert lut.shape == (32, 32, 2)
    np.testing.assert_allclose(specular_albedo(1.0, 0.0), [1.0, 0.0], atol=1e-4)
    assert lut[-1, 0] == pytest.approx([1.0, 0.0], abs=3e-3)           # n·v ≈ 1, smoothest
    assert np.all(lut.sum(-1) <= 1.0 + 1e-4) and np.all(lut >= 0)
    # [i, j]: n·v = (i + 0.5)/32, roughness = (j + 0.5)/32; grazing and rough loses energy.
    np.testing.assert_allclose(lut[4, 20], specular_albedo(4.5 / 32, 20.5 / 32), atol=1e-6)
    assert np.all(np.diff(lut[-1].sum(-1)) < 1e-6)                       # rougher loses more at n·v ≈ 1


def _brute_albedo(nv, r, n=1200):
    """∫ f_s (n·l) dω for F = 1 and F = F_c by midpoint quadrature in (θ_l, φ_l), float64 numpy."""
    a = max(r, brdf.MIN_ROUGHNESS) ** 2
    th = (np.arange(n) + 0.5) / n * (np.pi / 2)
    ph = (np.arange(2 * n) + 0.5) / (2 * n) * np.pi                   # symmetric in φ: half, doubled
    t, p = np.meshgrid(th, ph, indexing="ij")
    l = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    v = np.array([np.sqrt(1 - nv * nv), 0.0, nv])
    h = _unit(l + v)
    nh, vh, nl = h[..., 2], h @ v, l[..., 2]
    d = a * a / (np.pi * (nh * nh * (a * a - 1) + 1) ** 2)
    vis = 0.5 / (nl * np.sqrt(nv * nv * (1 - a * a) + a * a) + nv * np.sqrt(nl * nl * (1 - a * a) + a * a))
    f = d * vis * nl * np.sin(t) * (np.pi / 2 / n) * (np.pi / (2 * n)) * 2
    fc = (1 - vh) ** 5
    return np.array([(f * (1 - fc)).sum(), (f * fc).sum()])


@pytest.mark.parametrize("i,j", [(31, 31), (16, 16), (6, 24), (25, 12), (0, 31)])
def test_lut_matches_brute_force_quadrature(lut, i, j):
    np.testing.assert_allclose(lut[i, j], _brute_albedo((i + 0.5) / 32, (j + 0.5) / 32), atol=1e-3)


# --- the split sum against the Monte Carlo reference --------------------------------------------------

def _points(nv_min=0.15, seed=4):
    rng = np.random.default_rng(seed)
    n = _unit(rng.normal(size=(P, 3)))
    t = _unit(np.cross(n, _unit(rng.normal(size=(P, 3)))))
    nv = rng.uniform(nv_min, 1.0, P)
    v = nv[:, None] * n + np.sqrt(1 - nv * nv)[:, None] * t
    f = lambda x: jnp.asarray(x, jnp.float32)
    return (f(n), f(v), f(rng.random((P, 3))), f(rng.choice([0.0, 0.5, 1.0], (P, 1))), f(rng.random((P, 1))))


@pytest.mark.parametrize("model", [Model(), Model(multiscatter=True), Model(diffuse="burley"),
                                   Model(fresnel="dielectric")], ids=["gltf", "multiscatter", "burley", "dielectric"])
def test_split_sum_is_exact_in_a_constant_environment(constant_tables, model):
    env, sh = constant_tables
    if model.diffuse == "burley":
        sh = build_ibl(env, SMALL, model)
    n, v, base, metal, rough = _points()
    split = np.asarray(shade_ibl(sh, n, v, base, metal, rough, model))
    runs = np.stack([np.asarray(monte_carlo_radiance(env, n, v, base, metal, rough, model, MC_SAMPLES, jax.random.PRNGKey(k)))
                     for k in range(RUNS)])
    mc, se = runs.mean(0), runs.std(0, ddof=1) / math.sqrt(RUNS)
    # t statistic of the difference (Student t, RUNS - 1 dof), allowing the 32² LUT's
    # interpolation error (~1e-3) on top of the Monte Carlo noise.
    t = np.abs(split - mc) / np.sqrt(se ** 2 + (2e-3 * (1 + mc)) ** 2)
    assert np.mean(t > 4) < 0.01 and t.max() < 8
    assert abs(np.mean(split - mc)) < 4 * np.std(split - mc) / math.sqrt(split.size) + 1e-3


def test_occlusion_scales_both_terms(constant_tables):
    _, sh = constant_tables
    n, v, base, metal, rough = _points()
    full = shade_ibl(sh, n, v, base, metal, rough)
    half = shade_ibl(sh, n, v, base, metal, rough, occlusion=jnp.full((P, 1), 0.5))
    np.testing.assert_allclose(half, 0.5 * full, rtol=1e-6)
    assert np.all(np.asarray(shade_ibl(sh, n, -v, base, metal, rough)) == 0)     # n·v <= 0: dark


# --- differentiability -------------------------------------------------------------------------

def test_gradients_wrt_roughness_match_finite_differences(sky_tables):
    _, tabs32 = sky_tables
    with jax.enable_x64(True):
        tabs = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), tabs32)
        d = jnp.asarray(_unit(np.array([0.3, 0.5, -0.8])))
        for r in [0.13, 0.41, 0.77]:            # away from level and LUT knots (piecewise linear there)
            for fn in (lambda x: prefiltered_lookup(tabs, d, x).sum(),
                       lambda x: lookup_brdf_lut(tabs.lut, 0.37, x).sum()):
                g = jax.grad(fn)(r)
                fd = (fn(r + 1e-6) - fn(r - 1e-6)) / 2e-6
                assert np.isfinite(g) and g != 0 and g == pytest.approx(float(fd), rel=1e-5, abs=1e-9)


def test_gradients_wrt_environment_pixels_and_roughness(sky_tables):
    """The split sum is linear in the environment's pixels, so a finite difference of any size is exact."""
    env, _ = sky_tables
    n, v, base, metal, rough = (x[:16] for x in _points())
    rough = rough.at[:4, 0].set(jnp.array([0.0, 1e-4, 0.999, 1.0]))

    tiny = IBLSettings(lut_size=8, lut_samples=16, prefilter_levels=3, prefilter_resolution=8,
                       prefilter_samples=8, irradiance_resolution=4, env_resolution=16)

    @jax.jit
    def loss(rad, rough):
        return shade_ibl(build_ibl(Environment(rad), tiny), n, v, base, metal, rough).sum()

    g_rad, g_r = jax.grad(loss, argnums=(0, 1))(env.radiance, rough)
    assert np.all(np.isfinite(g_rad)) and np.all(np.isfinite(g_r)) and float(jnp.abs(g_rad).sum()) > 0
    dirn = jnp.asarray(np.random.default_rng(5).random(env.radiance.shape), jnp.float32)
    fd = loss(env.radiance + 0.5 * dirn, rough) - loss(env.radiance, rough)
    assert float(jnp.sum(g_rad * dirn)) * 0.5 == pytest.approx(float(fd), rel=1e-4)
    # roughness, away from the ends: a central difference along a random direction
    step = 1e-3 * jnp.asarray(np.random.default_rng(6).random(rough.shape), jnp.float32).at[:4].set(0.0)
    fd_r = (loss(env.radiance, rough + step) - loss(env.radiance, rough - step)) / 2.0
    assert float(jnp.sum(g_r * step)) == pytest.approx(float(fd_r), rel=1e-2)  # measured: 8e-4 apart


def test_brdf_tables_are_build_ibls_without_the_environment(sky_tables):
    """`brdf_tables` (multiscatter under punctual lights alone) holds exactly the BRDF tables
    `build_ibl` makes for an environment, and no light."""
    from pbrfit.lighting.ibl import brdf_tables

    _, full = sky_tables
    alone = brdf_tables(SMALL)
    for name in ("lut", "diffuse", "dielectric"):
        np.testing.assert_array_equal(np.asarray(getattr(alone, name)), np.asarray(getattr(full, name)), err_msg=name)
    assert not np.any(np.asarray(alone.irradiance)) and not np.any(np.asarray(alone.prefiltered))
    with jax.enable_x64(True):  # float32 tables with x64 on too: float32 shading is not promoted
        tables = brdf_tables(SMALL)
        assert {getattr(tables, name).dtype for name in ("lut", "diffuse", "dielectric", "irradiance")} == {
            jnp.dtype(jnp.float32)}


def test_prefiltered_roughness_derivative_at_the_ends_is_from_inside(sky_tables):
    """At roughness 0 and 1 (the ends of the level stack) the derivative is the one-sided one from
    inside, not half of it (a clip's at a tie), as `brdf.clamp_inward` keeps the BRDF's."""
    _, tables = sky_tables
    d = jnp.asarray([[0.3, 0.5, -0.8]]) / np.linalg.norm([0.3, 0.5, -0.8])
    f = jax.jit(lambda r: jnp.sum(prefiltered_lookup(tables, d, r)))
    h = 1e-3
    for end, inside in ((1.0, 1.0 - h), (0.0, h)):
        one_sided = (float(f(end)) - float(f(inside))) / (end - inside)
        assert float(jax.grad(f)(end)) == pytest.approx(one_sided, rel=0.02), end


def test_shading_is_finite_over_the_closed_domain(constant_tables):
    _, sh = constant_tables
    n = jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (5, 1))
    nv = jnp.array([0.0, 1e-7, 1e-3, 0.5, 1.0])
    v = jnp.stack([jnp.sqrt(1 - nv * nv), 0 * nv, nv], -1)

    def f(base, metal, rough):
        return shade_ibl(sh, n, v, base, metal, rough, Model(multiscatter=True)).sum()

    for r in (0.0, 1.0):
        for m in (0.0, 1.0):
            args = (jnp.full((5, 3), 1.0), jnp.full((5, 1), m), jnp.full((5, 1), r))
            out = f(*args)
            grads = jax.grad(f, argnums=(0, 1, 2))(*args)
            assert np.isfinite(out) and all(np.all(np.isfinite(g)) for g in grads)
    assert float(dot3(n, v)[0]) == 0.0


def test_layered_environment_is_read_through_its_colour_layer(tmp_path):
    import OpenImageIO as oiio

    sky = np.random.default_rng(2).random((4, 8, 3)).astype(np.float32)
    names = ["World.AO.R", "World.AO.G", "World.AO.B", "World.Combined.R", "World.Combined.G", "World.Combined.B"]
    spec = oiio.ImageSpec(8, 4, len(names), "float")
    spec.channelnames = names
    out = oiio.ImageOutput.create(str(tmp_path / "env.exr"))
    out.open(str(tmp_path / "env.exr"), spec)
    out.write_image(np.concatenate([np.full_like(sky, 5.0), sky], axis=-1))
    out.close()
    env = load_environment(tmp_path / "env.exr")
    np.testing.assert_allclose(np.asarray(env.radiance), sky, rtol=1e-6)


def test_gradients_finite_at_a_zero_direction_and_at_normal_incidence():
    """direction_to_uv at the zero vector (arctan2(0, 0)) and at the poles, and the albedo table's
    view direction at n·v = 1 (sqrt(1 - n·v²)), have finite derivatives."""
    from pbrfit.lighting.environment import direction_to_uv

    for d in ([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1e-20, 0.0]):
        jac = np.asarray(jax.jacfwd(direction_to_uv)(jnp.asarray(d, jnp.float32)))
        assert np.all(np.isfinite(jac)), (d, jac)
    np.testing.assert_allclose(np.asarray(direction_to_uv(jnp.zeros(3))), [0.5, 0.0])
    g = jax.grad(lambda c: specular_albedo(c, 0.5, samples=64).sum())
    assert np.isfinite(float(g(1.0)))  # was -inf
