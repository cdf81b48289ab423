"""Renderer: shading against independent closed forms, texture sampling, normal mapping."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit import brdf
from pbrfit.physics.lights import point_light
from pbrfit.physics.material import Material, apply_normal_map, material_at
from pbrfit.physics.model import Model
from pbrfit.render.shade import (RENDER_CHUNK, ViewInputs, light_arrays, radiance_view, render_rows, render_view,
                                 shade)
from pbrfit.physics.textures import bilinear_weights, build_mips, sample_bilinear


def _plane_view(n=6, light_pos=(0.3, -0.2, 2.0), intensity=10.0):
    """A unit plane z = 0 seen from a camera at (0, 0, 3); uv = (x + 1/2, y + 1/2) (row 0 = v = 0)."""
    xs = (np.arange(n) + 0.5) / n - 0.5
    gx, gy = np.meshgrid(xs, xs)
    pos = np.stack([gx, gy, np.zeros_like(gx)], -1).reshape(-1, 3)
    cam = np.array([0.0, 0.0, 3.0])
    view = cam - pos
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    light = point_light(light_pos, (1.0, 0.9, 0.8), intensity)
    light_l, light_rad = light_arrays([light], pos)
    p = pos.shape[0]
    vi = ViewInputs(
        pixel=jnp.arange(p, dtype=jnp.int32),
        uv=jnp.asarray(pos[:, :2] + 0.5, jnp.float32),
        normal=jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (p, 1)),
        tangent=jnp.tile(jnp.array([[1.0, 0.0, 0.0, 1.0]]), (p, 1)),
        view=jnp.asarray(view, jnp.float32),
        light_l=light_l,
        light_radiance=light_rad,
        shape=(n, n),
    )
    return vi, pos, cam, np.asarray(light_pos), intensity


def _closed_form(pos, cam, light_pos, intensity, base, metal, rough):
    """glTF Appendix B evaluated by hand in float64 numpy, per point."""
    out = []
    a = max(rough, brdf.MIN_ROUGHNESS) ** 2
    for p in pos:
        v = cam - p
        v /= np.linalg.norm(v)
        d = light_pos - p
        dist2 = d @ d
        l = d / np.sqrt(dist2)
        h = (v + l) / np.linalg.norm(v + l)
        nv, nl, nh, vh = v[2], l[2], h[2], v @ h
        D = a * a / (math.pi * (nh * nh * (a * a - 1) + 1) ** 2)
        V = 0.5 / (nl * math.sqrt(nv * nv * (1 - a * a) + a * a) + nv * math.sqrt(nl * nl * (1 - a * a) + a * a))
        f0 = 0.04 * (1 - metal) + np.asarray(base) * metal
        F = f0 + (1 - f0) * (1 - vh) ** 5
        f = (1 - F) * (1 - metal) * np.asarray(base) / math.pi + F * D * V
        E = np.array([1.0, 0.9, 0.8]) * intensity / dist2
        out.append(f * nl * E)
    return np.array(out)


@pytest.mark.parametrize("base,metal,rough", [((0.8, 0.3, 0.1), 0.0, 0.4), ((0.9, 0.7, 0.3), 1.0, 0.15), ((0.5, 0.5, 0.5), 0.3, 1.0)])
def test_plane_under_point_light_matches_closed_form(base, metal, rough):
    vi, pos, cam, light_pos, intensity = _plane_view()
    mat = Material.uniform(base, metal, rough, size=4)
    got = np.asarray(radiance_view(vi, mat, Model()))
    want = _closed_form(pos, cam, light_pos, intensity, base, metal, rough)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-6)


def test_render_view_places_pixels_and_alpha():
    vi, *_ = _plane_view(n=4)
    keep = ViewInputs(vi.pixel[::2], vi.uv[::2], vi.normal[::2], vi.tangent[::2], vi.view[::2],
                      vi.light_l[::2], vi.light_radiance[::2], vi.shape)
    img, alpha = render_view(keep, Material.uniform((0.5, 0.5, 0.5), 0.0, 0.5), exposure=1.0, color_space="srgb")
    assert img.shape == (4, 4, 3) and alpha.shape == (4, 4)
    flat_alpha = np.asarray(alpha).reshape(-1)
    assert flat_alpha[::2].tolist() == [1.0] * 8 and flat_alpha[1::2].tolist() == [0.0] * 8
    assert np.all(np.asarray(img).reshape(-1, 3)[1::2] == 0) and np.all(np.asarray(img).reshape(-1, 3)[::2] > 0)
    assert float(jnp.max(img)) <= 1.0


def test_chunked_radiance_equals_whole():
    vi, *_ = _plane_view(n=7)
    mat = Material.uniform((0.2, 0.6, 0.9), 0.5, 0.3)
    whole = radiance_view(vi, mat)
    chunked = radiance_view(vi, mat, chunk=10)
    # equal to float32 rounding: the two programs are compiled for different shapes, and near a
    # highlight's peak one ulp of n·h moves D by 2e-5 relative (roughness 0.3)
    np.testing.assert_allclose(np.asarray(chunked), np.asarray(whole), rtol=1e-4)


def test_views_of_nearby_sizes_share_one_compile():
    """A capture's views hit different numbers of pixels: each is padded to the next of 2^k and
    1.5 · 2^k rows (`render_rows`), so views of 400 to 512 pixels compile once, and each view's
    radiance is that of its own pixels alone."""
    from pbrfit.render import shade as shade_module
    from pbrfit.render.views import view_rows

    assert [render_rows(n) for n in (1, 256, 257, 385, 513, 769, 5761, 40_000, 65_536, 65_537, 10**6)] == [
        256, 256, 384, 512, 768, 1024, 6144, 49_152, RENDER_CHUNK, 2 * RENDER_CHUNK, 16 * RENDER_CHUNK]
    vi, *_ = _plane_view(n=24)  # 576 pixels
    mat = Material.uniform((0.2, 0.6, 0.9), 0.5, 0.3, size=4)
    model = Model(diffuse="burley")
    whole = np.asarray(radiance_view(vi, mat, model))
    compiled = shade_module._radiance_chunk_jit._cache_size()
    for n in (400, 487, 512):
        rows = np.sort(np.random.default_rng(n).choice(576, n, replace=False))
        got = radiance_view(view_rows(vi, rows), mat, model)
        assert got.shape == (n, 3)
        np.testing.assert_allclose(np.asarray(got), whole[rows], rtol=1e-6, atol=1e-7)
    assert shade_module._radiance_chunk_jit._cache_size() <= compiled + 1  # one program of 512 rows (or none: cached)


def test_render_view_pads_a_view_and_draws_its_own_pixels_alone():
    """`render_view` pads a view's rows to `render_rows` of them (repeats of its last hit, which
    write the same value again): a view of 400 of a frame's 576 hit pixels renders as the whole
    view does on them, and nothing elsewhere; views of 400 and 487 pixels share one shading
    program; per-pixel integrals are padded with the rows."""
    from pbrfit.lighting.pixel_ibl import PixelIBL, lobes_for
    from pbrfit.render import shade as shade_module
    from pbrfit.render.views import view_rows

    vi, *_ = _plane_view(n=24)
    mat = Material.uniform((0.2, 0.6, 0.9), 0.5, 0.3, size=4)
    encoding = dict(exposure=0.5, tonemap="aces_hill", color_space="srgb")
    image, alpha = (np.asarray(a) for a in render_view(vi, mat, **encoding))
    compiled = None
    for n in (400, 487):
        rows = np.sort(np.random.default_rng(n).choice(576, n, replace=False))
        got, got_alpha = (np.asarray(a).reshape(576, -1) for a in render_view(view_rows(vi, rows), mat, **encoding))
        np.testing.assert_allclose(got[rows], image.reshape(576, 3)[rows], rtol=1e-6, atol=1e-7)
        assert np.all(got_alpha[rows] == 1.0) and np.sum(got_alpha) == n and np.sum(np.abs(got)) > 0
        assert np.all(np.delete(got, rows, axis=0) == 0.0)
        compiled = compiled or shade_module._radiance_chunk_jit._cache_size()
    assert shade_module._radiance_chunk_jit._cache_size() == compiled  # the 487-pixel view compiled nothing new
    model = Model(ibl="per_pixel")
    table = PixelIBL(jnp.ones((400, 3, len(lobes_for(model)), 3), jnp.float32), lobes_for(model))
    lit, _ = render_view(view_rows(vi, rows[:400]), mat, model, table)
    assert np.all(np.isfinite(np.asarray(lit)))


def test_shade_gradients_finite_at_extremes():
    vi, *_ = _plane_view(n=3)
    p = vi.num_pixels

    def loss(b, m, r):
        return jnp.sum(shade(vi.normal, vi.view, vi.light_l, vi.light_radiance, b, m, r))

    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))  # (eagerly, each primitive compiled on its own)
    for val in (0.0, 1.0):
        grads = grad(jnp.full((p, 3), val), jnp.full((p, 1), val), jnp.full((p, 1), val))
        assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)


def test_material_gradient_at_its_bounds_is_from_inside():
    """`radiance_view` clips the sampled material to [0, 1] with the derivative from inside at 0 and
    1 (a clip's is half of it there): metallic 0, roughness 1 and white base colour keep their
    whole gradient."""
    vi, *_ = _plane_view(n=3)
    loss = jax.jit(lambda m: jnp.sum(radiance_view(vi, m, Model())))
    h = 1e-3
    for base, metal, rough, field, step in ((0.5, 0.0, 0.5, "metallic", h), (0.5, 0.5, 1.0, "roughness", -h),
                                            (1.0, 0.5, 0.5, "base_color", -h)):
        mat = Material.uniform((base,) * 3, metal, rough, size=2)
        grad = float(jnp.sum(getattr(jax.grad(loss)(mat), field)))
        moved = dataclasses.replace(mat, **{field: getattr(mat, field) + step})
        one_sided = (float(loss(moved)) - float(loss(mat))) / step
        assert grad == pytest.approx(one_sided, rel=0.02), field


# --- textures --------------------------------------------------------------------------------
def test_texel_centres_return_texel_values():
    tex = jnp.arange(3 * 4 * 2, dtype=jnp.float32).reshape(3, 4, 2)
    i, j = np.meshgrid(np.arange(3), np.arange(4), indexing="ij")
    uv = np.stack([(j + 0.5) / 4, (i + 0.5) / 3], -1)
    np.testing.assert_allclose(np.asarray(sample_bilinear(tex, uv)), np.asarray(tex), atol=1e-5)


def test_resample_map_box_filters_whole_factors():
    from pbrfit.physics.textures import resample_map

    small = np.random.default_rng(0).random((4, 6, 1)).astype(np.float32)
    big = np.repeat(np.repeat(small, 2, axis=0), 3, axis=1)  # each texel repeated 2 x 3
    np.testing.assert_allclose(resample_map(big, (4, 6)), small, rtol=1e-6)  # a held map comes back
    np.testing.assert_allclose(resample_map(big, (1, 1))[0, 0], big.mean((0, 1)), rtol=1e-6)
    assert resample_map(big, (5, 7)).shape == (5, 7, 1) and resample_map(small, (8, 12)).shape == (8, 12, 1)


def test_bilinear_midpoint_and_wrap_modes():
    tex = jnp.array([[[0.0], [1.0]], [[2.0], [3.0]]])  # row 0 = v = 0
    mid = sample_bilinear(tex, jnp.array([0.5, 0.5]))
    assert float(mid[0]) == pytest.approx(1.5)
    # at u = 0 the sample lies half-way between the last and first column when repeating
    assert float(sample_bilinear(tex, jnp.array([0.0, 0.25]), "repeat")[0]) == pytest.approx(0.5)
    assert float(sample_bilinear(tex, jnp.array([0.0, 0.25]), "clamp")[0]) == pytest.approx(0.0)
    # v = 0.25 is row 0's centre: values from the top row only
    assert float(sample_bilinear(tex, jnp.array([0.75, 0.25]), "clamp")[0]) == pytest.approx(1.0)
    idx, w = bilinear_weights(jnp.array([[0.3, 0.6]]), (2, 2), "clamp")
    assert float(jnp.sum(w)) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="unknown wrap"):
        bilinear_weights(jnp.zeros(2), (2, 2), "mirror")


def test_sampling_gradient_matches_finite_difference():
    key = jax.random.PRNGKey(0)
    tex = jax.random.uniform(key, (5, 6, 1))
    uv = jnp.array([0.37, 0.61])
    g = jax.grad(lambda u: sample_bilinear(tex, u)[0])(uv)
    eps = 1e-3
    fd = [(sample_bilinear(tex, uv + eps * e)[0] - sample_bilinear(tex, uv - eps * e)[0]) / (2 * eps) for e in jnp.eye(2)]
    np.testing.assert_allclose(np.asarray(g), np.asarray(fd), rtol=1e-2)


def test_mips_preserve_mean():
    tex = jax.random.uniform(jax.random.PRNGKey(1), (8, 8, 3))
    mips = build_mips(tex)
    assert [m.shape[0] for m in mips] == [8, 4, 2, 1]
    np.testing.assert_allclose(np.asarray(mips[-1][0, 0]), np.asarray(tex.mean(axis=(0, 1))), rtol=1e-5)


# --- normal mapping ------------------------------------------------------------------------------
def test_flat_normal_map_leaves_normal_unchanged():
    n = jnp.array([[0.0, 0.6, 0.8]])
    t = jnp.array([[1.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(np.asarray(apply_normal_map(n, t, jnp.array([[0.0, 0.0, 1.0]]))), np.asarray(n), atol=1e-6)


def test_directx_convention_mirrors_bump_in_bitangent():
    n = jnp.array([[0.0, 0.0, 1.0]])
    t = jnp.array([[1.0, 0.0, 0.0, 1.0]])
    bump = jnp.array([[0.3, 0.4, 0.866]])
    gl = apply_normal_map(n, t, bump, "opengl")
    dx = apply_normal_map(n, t, bump, "directx")
    # B = cross(N, T) * w = +y: the OpenGL map tilts towards +y, the DirectX one towards -y.
    assert float(gl[0, 1]) > 0 and float(dx[0, 1]) < 0
    np.testing.assert_allclose(np.asarray(gl[0, [0, 2]]), np.asarray(dx[0, [0, 2]]), atol=1e-6)
    np.testing.assert_allclose(float(gl[0, 1]), -float(dx[0, 1]), atol=1e-6)
    # flipping handedness mirrors too
    t_left = jnp.array([[1.0, 0.0, 0.0, -1.0]])
    np.testing.assert_allclose(np.asarray(apply_normal_map(n, t_left, bump)), np.asarray(dx), atol=1e-6)


def test_material_uniform_and_sampling():
    mat = Material.uniform((0.1, 0.2, 0.3), 0.5, 0.7, size=3)
    s = material_at(mat, jnp.array([[0.1, 0.9], [0.5, 0.5]]))
    np.testing.assert_allclose(np.asarray(s.base_color), [[0.1, 0.2, 0.3]] * 2, rtol=1e-6)
    assert s.normal is None
    with pytest.raises(ValueError, match="metallic"):
        Material(jnp.zeros((2, 2, 3)), jnp.zeros((2, 2)), jnp.zeros((2, 2, 1)))
    with pytest.raises(ValueError, match=r"roughness must have shape \(H, W, 1\) with H, W >= 1, got \(0, 2, 1\)"):
        Material(jnp.zeros((2, 2, 3)), jnp.zeros((2, 2, 1)), jnp.zeros((0, 2, 1)))
    grey = Material.uniform(0.25, 0.0, 0.5, size=2)
    np.testing.assert_array_equal(np.asarray(grey.base_color), np.full((2, 2, 3), 0.25, np.float32))
    for args, match in ((((0.5, 0.5), 0.0, 0.5), "base_color must be R, G, B or one value"),
                        (((0.5,) * 3, 0.0, 0.5, 0), "size must be an integer >= 1, got 0")):
        with pytest.raises(ValueError, match=match):
            Material.uniform(*args)
