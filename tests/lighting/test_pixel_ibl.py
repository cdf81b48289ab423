"""Per-pixel IBL integrals: the regrouped BRDF against the Monte Carlo reference, the roughness
spline, gradients at the extremes, and a fit that uses them."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit.lighting.environment import Environment, procedural_sky
from pbrfit.fitting.api import fit_observations
from pbrfit.physics.model import Model
from pbrfit.lighting.montecarlo import monte_carlo_radiance
from pbrfit.fitting.observations import observations_from_views
from pbrfit.lighting.pixel_ibl import (PixelIBL, PixelIBLSettings, interpolate_lobes, lobes_for, pixel_ibl,
                              shade_pixel_ibl)
from pbrfit.physics.material import Material
from pbrfit.render.shade import ViewInputs, radiance_view, shade

SKY = procedural_sky(64, sun_elevation_deg=40.0, sun_radius_deg=4.0, sun_illuminance=4.0)


def _points(count=48, seed=0):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(count, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where(np.sum(n * v, 1, keepdims=True) < 0, -v, v)
    return n.astype(np.float32), v.astype(np.float32)


def test_lobes_follow_the_model():
    assert lobes_for(Model()) == ("dv", "dv_s", "lambert_s")
    assert lobes_for(Model(metallic=False, fresnel="dielectric")) == ("dv_fd", "lambert_fd")
    assert lobes_for(Model(fresnel="dielectric")) == ("dv", "dv_s", "dv_fd", "lambert_s", "lambert_fd")
    assert lobes_for(Model(specular=False)) == ("lambert",)
    assert lobes_for(Model(diffuse="burley", multiscatter=True)) == ("dv", "dv_s", "burley", "dfg_scale", "dfg_bias")
    assert lobes_for(Model(diffuse="none")) == ("dv", "dv_s")


MODELS = [
    Model(),
    Model(fresnel="dielectric", distribution="beckmann"),
    Model(diffuse="burley", multiscatter=True, geometry="schlick_ggx_direct"),
]


@pytest.mark.parametrize("model", MODELS, ids=["gltf", "dielectric-beckmann", "burley-multiscatter"])
def test_matches_the_monte_carlo_reference(model):
    """Σ c_k I_k equals ∫ f L cos for random materials, on and between the roughness levels."""
    n, v = _points()
    count = n.shape[0]
    ibl = pixel_ibl(SKY, n, v, model, PixelIBLSettings(levels=17, samples=512))
    rng = np.random.default_rng(1)
    base = rng.uniform(size=(count, 3)).astype(np.float32)
    metal = (rng.uniform(size=(count, 1)) > 0.5).astype(np.float32)
    for r in (0.5, 0.27, 0.8):  # a level, and two points between levels
        rough = np.full((count, 1), r, np.float32)
        got = np.asarray(shade_pixel_ibl(ibl, base, metal, rough, model))
        ref = np.asarray(monte_carlo_radiance(SKY, n, v, base, metal, rough, model, samples=8192))
        rel = np.sum(np.abs(got - ref)) / np.sum(np.abs(ref))
        assert rel < 0.015, (r, rel)


def test_lambert_under_a_white_sky_is_one():
    n, v = _points(16)
    white = Environment(jnp.ones((32, 64, 3), jnp.float32))
    ibl = pixel_ibl(white, n, v, Model(specular=False), PixelIBLSettings(levels=2, samples=1024))
    np.testing.assert_allclose(np.asarray(ibl.table), 1.0, atol=0.01)


def test_progress_counts_pixels():
    n, v = _points(20)
    calls = []
    pixel_ibl(SKY, n, v, Model(), PixelIBLSettings(levels=3, samples=16), chunk=7,
              progress=lambda done, total: calls.append((done, total)))
    assert calls == [(7, 20), (14, 20), (20, 20)]


def test_chunks_do_not_change_the_integrals():
    """Each pixel draws its own samples: chunking moves only float rounding (which a sample
    grazing the sun's edge can amplify to a few 1e-3), while another seed moves the estimate."""
    n, v = _points(20)
    a = np.asarray(pixel_ibl(SKY, n, v, Model(), PixelIBLSettings(levels=3, samples=16), chunk=7).table)
    b = np.asarray(pixel_ibl(SKY, n, v, Model(), PixelIBLSettings(levels=3, samples=16), chunk=20).table)
    c = np.asarray(pixel_ibl(SKY, n, v, Model(), PixelIBLSettings(levels=3, samples=16, seed=1), chunk=20).table)
    scale = np.abs(b).max(axis=(1, 2, 3), keepdims=True)
    assert np.max(np.abs(a - b) / scale) < 1e-2
    assert np.max(np.abs(c - b) / scale) > 5e-2


def test_tables_are_cached_by_everything_they_depend_on(tmp_path, monkeypatch):
    import pbrfit.lighting.pixel_ibl as module

    n, v = _points(10)
    settings = PixelIBLSettings(levels=3, samples=8)
    first = pixel_ibl(SKY, n, v, Model(), settings, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("pixel-ibl-*.npy"))) == 1

    def fail(*args, **kwargs):
        raise AssertionError("integrated again")

    monkeypatch.setattr(module, "integrate_lobes", fail)
    again = pixel_ibl(SKY, n, v, Model(), settings, cache_dir=tmp_path)
    np.testing.assert_array_equal(np.asarray(again.table), np.asarray(first.table))
    for changed in (dict(settings=PixelIBLSettings(levels=3, samples=16)), dict(model=Model(fresnel="dielectric")),
                    dict(v=np.roll(v, 1, axis=0)), dict(n=np.roll(n, 1, axis=0)),
                    dict(env=procedural_sky(64, sun_elevation_deg=20.0)),
                    dict(env=dataclasses.replace(SKY, rotation_deg=30.0)), dict(env=dataclasses.replace(SKY, world_up="+z"))):
        args = dict(env=SKY, n=n, v=v, model=Model(), settings=settings, cache_dir=tmp_path)
        args.update(changed)
        with pytest.raises(AssertionError, match="integrated again"):
            pixel_ibl(**args)
    next(tmp_path.glob("pixel-ibl-*.npy")).write_bytes(b"damaged")  # a damaged file is recomputed
    with pytest.raises(AssertionError, match="integrated again"):
        pixel_ibl(SKY, n, v, Model(), settings, cache_dir=tmp_path)


def test_spline_is_exact_on_levels_and_on_quadratic_tables():
    levels = 9
    r = np.linspace(0.0, 1.0, levels)
    table = jnp.asarray(np.stack([0.3 + 2.0 * r - 1.5 * r * r, np.cos(3 * r)], -1)[None, :, :, None] * np.ones(3),
                        jnp.float32)
    at_levels = interpolate_lobes(jnp.repeat(table, levels, 0), jnp.asarray(r, jnp.float32))
    np.testing.assert_allclose(np.asarray(at_levels), np.asarray(table[0]), atol=1e-6)
    x = np.linspace(0.0, 1.0, 101).astype(np.float32)
    got = np.asarray(interpolate_lobes(jnp.repeat(table, x.size, 0), jnp.asarray(x)))
    np.testing.assert_allclose(got[:, 0, 0], 0.3 + 2.0 * x - 1.5 * x * x, atol=1e-5)  # quadratic: exact
    np.testing.assert_allclose(got[:, 1, 0], np.cos(3 * x), atol=2e-3)  # smooth: O(h³), ends included
    # C¹: the derivative is continuous across a level
    d = jax.vmap(jax.grad(lambda s: interpolate_lobes(table, s[None])[0, 1, 0]))
    left, right = np.asarray(d(jnp.asarray([0.5 - 1e-4, 0.5 + 1e-4], jnp.float32)))
    assert abs(left - right) < 1e-2 * max(1.0, abs(left))


def test_gradients_are_finite_and_match_differences_at_the_extremes():
    n, v = _points(6, seed=3)
    ibl = pixel_ibl(SKY, n, v, Model(), PixelIBLSettings(levels=9, samples=32))

    def radiance(x):
        return jnp.sum(shade_pixel_ibl(ibl, x[:, 0:3], x[:, 3:4], x[:, 4:5], Model()))

    for base, metal, rough in [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.5, 0.0, 0.125), (0.2, 1.0, 0.03)]:
        x = jnp.tile(jnp.asarray([[base] * 3 + [metal, rough]], jnp.float32), (n.shape[0], 1))
        g = np.asarray(jax.grad(radiance)(x))
        assert np.all(np.isfinite(g))
        for c in range(5):
            e = np.zeros(5, np.float32)
            e[c] = 1e-3
            lo, hi = np.clip(np.asarray(x) - e, 0, 1), np.clip(np.asarray(x) + e, 0, 1)
            fd = (float(radiance(jnp.asarray(hi))) - float(radiance(jnp.asarray(lo)))) / float(hi[0, c] - lo[0, c])
            assert abs(np.sum(g[:, c]) - fd) <= 2e-2 * max(1.0, abs(fd)), (base, metal, rough, c)


def test_shade_dispatches_and_checks_the_lobes():
    n, v = _points(8)
    model = Model(ibl="per_pixel")
    ibl = pixel_ibl(SKY, n, v, model, PixelIBLSettings(levels=3, samples=8))
    p = n.shape[0]
    zero_lights = jnp.zeros((p, 1, 3), jnp.float32)
    base, metal, rough = jnp.full((p, 3), 0.5), jnp.zeros((p, 1)), jnp.full((p, 1), 0.4)
    out = shade(jnp.asarray(n), jnp.asarray(v), zero_lights, zero_lights, base, metal, rough, model, ibl)
    np.testing.assert_allclose(np.asarray(out), np.asarray(shade_pixel_ibl(ibl, base, metal, rough, model)), rtol=1e-6)
    with pytest.raises(ValueError, match="lobes"):
        shade_pixel_ibl(ibl, base, metal, rough, Model(fresnel="dielectric"))
    with pytest.raises(ValueError, match="per_pixel"):
        shade(jnp.asarray(n), jnp.asarray(v), zero_lights, zero_lights, base, metal, rough, model, None)
    with pytest.raises(ValueError, match="levels"):
        PixelIBLSettings(levels=1)
    # beyond the int32 counters' reach: refused as the command line refuses it
    with pytest.raises(ValueError, match=r"levels must be from 2 to 256, got 257"):
        PixelIBLSettings(levels=257)
    with pytest.raises(ValueError, match=r"samples must be from 1 to 1048576, got 1048577"):
        PixelIBLSettings(samples=(1 << 20) + 1)


def test_chunked_rendering_carries_each_pixels_rows():
    views = _env_views(1, res=12)
    vi = views[0]
    model = Model(ibl="per_pixel")
    ibl = pixel_ibl(ZUP_SKY, np.asarray(vi.normal), np.asarray(vi.view), model, PixelIBLSettings(levels=3, samples=8))
    material = Material.uniform((0.6, 0.5, 0.4), 0.0, 0.35)
    whole = np.asarray(radiance_view(vi, material, model, ibl))
    chunked = np.asarray(radiance_view(vi, material, model, ibl, chunk=7))
    np.testing.assert_allclose(chunked, whole, rtol=1e-6, atol=1e-7)
    direct = shade_pixel_ibl(ibl, jnp.full((vi.num_pixels, 3), jnp.asarray([0.6, 0.5, 0.4])),
                             jnp.zeros((vi.num_pixels, 1)), jnp.full((vi.num_pixels, 1), 0.35), model)
    np.testing.assert_allclose(whole, np.asarray(direct), rtol=1e-5, atol=1e-7)


# --- a fit that needs it -------------------------------------------------------------------------

ZUP_SKY = procedural_sky(64, sun_elevation_deg=35.0, sun_radius_deg=4.0, sun_illuminance=6.0, world_up="+z")


def _env_views(n_views=4, res=20):
    """A plane z = 0 (|x|, |y| < 1) seen from n_views cameras, lit only by `ZUP_SKY`."""
    views = []
    f = 0.5 * res / math.tan(math.radians(22.5))
    for k in range(n_views):
        az = 2 * math.pi * k / n_views + 0.4
        el = math.radians(40 + 15 * (k % 2))
        eye = 2.9 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        rot = np.stack([right, np.cross(right, fwd), -fwd], 1)
        j, i = np.meshgrid(np.arange(res) + 0.5, np.arange(res) + 0.5)
        d = np.stack([(j - res / 2) / f, -(i - res / 2) / f, -np.ones_like(j)], -1) @ rot.T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        pos = eye + (-eye[2] / d[..., 2])[..., None] * d
        flat = np.flatnonzero(((np.abs(pos[..., 0]) < 0.999) & (np.abs(pos[..., 1]) < 0.999)).reshape(-1))
        p = pos.reshape(-1, 3)[flat]
        vv = eye - p
        vv /= np.linalg.norm(vv, axis=-1, keepdims=True)
        m = len(flat)
        views.append(ViewInputs(
            pixel=jnp.asarray(flat, jnp.int32), uv=jnp.asarray(p[:, :2] / 2 + 0.5, jnp.float32),
            normal=jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (m, 1)),
            tangent=jnp.tile(jnp.array([[1.0, 0.0, 0.0, 1.0]]), (m, 1)),
            view=jnp.asarray(vv, jnp.float32), light_l=jnp.zeros((m, 1, 3)), light_radiance=jnp.zeros((m, 1, 3)),
            shape=(res, res)))
    return views


def test_uniform_fit_on_ground_truth_images_beats_the_split_sum():
    """Images rendered by the Monte Carlo reference: the per-pixel fit recovers the material, the
    split sum's approximation biases it."""
    from pbrfit.lighting.ibl import build_ibl

    views = _env_views()
    truth = dict(base=np.float32([0.75, 0.45, 0.2]), metal=1.0, rough=0.3)
    normal, view = (jnp.concatenate([getattr(vi, name) for vi in views]) for name in ("normal", "view"))
    m = normal.shape[0]  # every view's pixels in one call (one compile; the same values at any batch)
    rad = np.asarray(monte_carlo_radiance(ZUP_SKY, normal, view, np.tile(truth["base"], (m, 1)),
                                          np.full((m, 1), truth["metal"], np.float32),
                                          np.full((m, 1), truth["rough"], np.float32), samples=4096))
    images = []
    for vi, part in zip(views, np.split(rad, np.cumsum([vi.num_pixels for vi in views])[:-1])):
        img = np.zeros((vi.shape[0] * vi.shape[1], 3), np.float32)
        img[np.asarray(vi.pixel)] = part
        images.append(img.reshape(vi.shape + (3,)))
    obs = observations_from_views(views, images)
    errors = {}
    for mode in ("split_sum", "per_pixel"):
        model = Model(ibl=mode)
        ibl = (build_ibl(ZUP_SKY, model=model) if mode == "split_sum" else
               pixel_ibl(ZUP_SKY, np.asarray(obs.normal), np.asarray(obs.view), model, PixelIBLSettings(samples=256)))
        result = fit_observations(obs, model=model, ibl=ibl, maps="none")
        got = result.report["material"]
        errors[mode] = max(np.max(np.abs(np.asarray(got["base_color"]) - truth["base"])),
                           abs(got["metallic"] - truth["metal"]), abs(got["roughness"] - truth["rough"]))
    assert errors["per_pixel"] < 0.01, errors
    assert errors["per_pixel"] < 0.5 * errors["split_sum"], errors


def test_per_pixel_fits_refuse_fitted_normals():
    views = _env_views(2, res=8)
    obs = observations_from_views(views, [np.zeros(vi.shape + (3,), np.float32) for vi in views])
    table = PixelIBL(jnp.zeros((obs.num_pixels, 2, 3, 3)), lobes_for(Model()))
    with pytest.raises(ValueError, match="normals"):
        fit_observations(obs, model=Model(ibl="per_pixel"), ibl=table, fit=("base_color", "normal"))
