"""Pixel footprints: n × n samples per pixel (`pbrfit.fitting.observations`, `pbrfit.fitting.objective`).

A small supersampled flash capture (data_synth's plane-flash: 2 × 2 supersampled 16-bit sRGB
PNGs, noiseless here) is synthesised once for the module.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit.fitting.api import fit, map_rmse
from pbrfit.render.views import model_for_capture
from pbrfit.fitting.passes import PROBE_STEPS, SEARCH_AFTER
from pbrfit.scene.camera import Camera
from pbrfit.scene.gbuffer import compute_gbuffer
from pbrfit.io.material_files import read_material
from pbrfit.fitting.observations import PIXEL_FIELDS, coverage_counts, observations_from_capture, texel_layout
from pbrfit.scene.camera import pixel_offsets, sample_camera
from pbrfit.scene.capture import load_capture
from pbrfit.fitting.sharding import pad_observations, pad_pixel_rows
from pbrfit.fitting.objective import Problem, linearize, pixel_residuals, texel_grid
from pbrfit.fitting.stencil import data_blocks, data_neighbour_blocks, stencil_covers, with_stencil
from pbrfit.fitting.normal_matrix import (NEIGHBOUR_OFFSETS, gauss_newton_factors, gn_product, gradient, neighbour_blocks,
                                  normal_blocks)

MAP = (8, 8)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize

    out = tmp_path_factory.mktemp("footprint") / "cap"
    synthesize(make_scene("plane-flash", seed=3, size=32, views=4, texture_size=MAP[0], noise=0.0), out)
    return out


@pytest.fixture(scope="module")
def capture(capture_dir):
    return load_capture(capture_dir)


def test_a_sample_camera_looks_through_its_offset_of_each_pixel():
    """Each pixel centre's ray of `sample_camera(camera, offset)` projects, in the original
    camera, to that pixel's corner plus the offset (off-centre principal point, fx != fy)."""
    turn = np.eye(4)
    turn[:3, :3] = [[0.6, 0.0, 0.8], [0.0, 1.0, 0.0], [-0.8, 0.0, 0.6]]
    turn[:3, 3] = [0.3, -0.2, 2.0]
    camera = Camera(turn, 9.0, 7.0, 3.1, 2.4, 6, 5)
    for offset in ((0.25, 0.75), (0.9, 0.1)):
        origins, dirs = sample_camera(camera, offset).rays()
        xy = camera.project(origins + 2.0 * dirs)
        jj, ii = np.meshgrid(np.arange(6), np.arange(5))
        np.testing.assert_allclose(xy, np.stack([jj + offset[0], ii + offset[1]], -1), atol=1e-9)


def test_pixel_offsets_are_subpixel_centres():
    np.testing.assert_array_equal(pixel_offsets(1), [[0.5, 0.5]])
    np.testing.assert_array_equal(pixel_offsets(2), [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    third = np.array([1.0, 3.0, 5.0]) / 6.0
    np.testing.assert_allclose(pixel_offsets(3), np.stack(np.meshgrid(third, third), -1).reshape(9, 2), atol=1e-7)
    with pytest.raises(ValueError, match="pixel_samples"):
        observations_from_capture(None, pixel_samples=0)


def test_samples_are_the_pixels_of_a_camera_with_twice_the_resolution(capture):
    """Sample (x, y) of pixel (i, j) is the ray through pixel (2i + y, 2j + x) of the same view at
    twice the resolution: the offsets run right and down, as rows and columns do."""
    obs = observations_from_capture(capture, pixel_samples=2)
    assert obs.samples == 4 and obs.num_rows == 4 * obs.num_pixels
    frame = capture.frames[1]
    cam = frame.camera
    fine = Camera(cam.c2w, 2 * cam.fx, 2 * cam.fy, 2 * cam.cx, 2 * cam.cy, 2 * cam.width, 2 * cam.height)
    g = compute_gbuffer(capture.mesh, fine, ())
    sel = np.flatnonzero(np.asarray(obs.view_index) == 1)
    pix = np.asarray(obs.pixel)[sel].reshape(-1, 4)
    assert np.all(pix == pix[:, :1])  # a pixel's samples are consecutive rows
    i, j = pix[:, 0] // cam.width, pix[:, 0] % cam.width
    uv = np.asarray(obs.uv)[sel].reshape(-1, 4, 2)
    for s, (x, y) in enumerate([(0, 0), (1, 0), (0, 1), (1, 1)]):
        np.testing.assert_allclose(uv[:, s], g.uv[2 * i + y, 2 * j + x], atol=1e-6)
    # every sample's target is its pixel's value
    target = np.asarray(obs.target)[sel].reshape(-1, 4, 3)
    assert np.all(target == target[:, :1])
    # coverage counts pixels: once per texel however many of the pixel's samples read it
    layout = texel_layout(obs, MAP)
    rows, pixels = coverage_counts(layout), coverage_counts(layout, obs.samples)
    assert np.all(pixels <= rows) and np.all(rows <= 4 * pixels) and 4 * pixels.sum() > rows.sum()


def _problem(obs, capture, loss="l2"):
    layout = texel_layout(obs, MAP)
    t = MAP[0] * MAP[1]
    return Problem(obs, layout.index, layout.weight, jnp.ones((t, 5)), jnp.zeros((1, 2), jnp.int32), jnp.zeros(1),
                   jnp.asarray(0.0), jnp.asarray(0.02), None, model_for_capture(capture), loss)


#: The dense Jacobian of the pixel residuals (the tests' reference), jitted: one compile per
#: problem shape instead of one per operation.
_dense_jacobian = jax.jit(lambda x, problem: jax.jacfwd(lambda v: pixel_residuals(v, problem).reshape(-1))(x))

@pytest.mark.parametrize("loss", ["l2", "huber"])
def test_structure_is_exact_with_samples(capture, loss):
    """Residuals, per-sample Jacobians, gradient, normal blocks and JᵀJ v against the dense
    Jacobian of the pixel residuals (sRGB images: the encoding's Jacobian is in the chain; with
    a robust loss, the loss's too). Samples of one pixel share texels, so the blocks need the
    taps' Jacobians summed per texel before squaring."""
    obs = observations_from_capture(capture, pixel_samples=2)
    keep = np.flatnonzero(np.asarray(obs.view_index) == 0)[: 4 * 60]
    obs = dataclasses.replace(obs, **{k: getattr(obs, k)[keep] for k in PIXEL_FIELDS})
    problem = _problem(obs, capture, loss)
    t = problem.num_texels
    x = jnp.asarray(np.random.default_rng(0).uniform(0.1, 0.9, (t, 5)), jnp.float32)
    r, jac, _ = jax.jit(linearize)(x, problem)
    assert r.shape == (60, 3) and jac.shape == (240, 3, 5)
    dense = np.asarray(_dense_jacobian(x, problem)).reshape(-1, t * 5)
    np.testing.assert_allclose(np.asarray(r), np.asarray(pixel_residuals(x, problem)), atol=1e-6)
    jtj = dense.T @ dense
    want = np.stack([jtj[5 * k:5 * k + 5, 5 * k:5 * k + 5] for k in range(t)])
    scale = np.abs(jtj).max()
    blocks = jax.jit(normal_blocks)
    np.testing.assert_allclose(np.asarray(blocks(jac, problem)), want, atol=1e-5 * scale)
    # the plain Σ w² JᵀJ over rows would miss the cross terms of samples that read one texel
    rows = np.asarray(jnp.einsum("rci,rcj,rk->rkij", jac, jac, problem.weight ** 2))
    assert np.abs(rows.sum(axis=(0, 1)) - want.sum(axis=0)).max() > 1e-2 * scale
    g = np.asarray(jax.jit(gradient)(r, jac, x, problem)).reshape(-1)
    np.testing.assert_allclose(g, dense.T @ np.asarray(r).reshape(-1), atol=1e-5 * np.abs(g).max())
    v = jnp.asarray(np.random.default_rng(1).normal(size=(t, 5)), jnp.float32)
    jv = np.asarray(jax.jit(lambda j, v, p: gn_product(gauss_newton_factors(j, p), v, p))(jac, v, problem)).reshape(-1)
    np.testing.assert_allclose(jv, jtj @ np.asarray(v).reshape(-1), atol=1e-5 * np.abs(jv).max())
    # padding for devices keeps whole pixels: a multiple of 7 pixels, 4 rows each, all inert
    padded, real = pad_observations(obs, 7)
    assert (real, padded.num_rows, padded.num_pixels) == (240, 252, 63)
    index, weight = pad_pixel_rows(problem.index, problem.weight, 7, samples=4)
    bigger = dataclasses.replace(problem, obs=padded, index=index, weight=weight)
    r2, jac2, _ = jax.jit(linearize)(x, bigger)
    assert np.all(np.asarray(r2[60:]) == 0.0) and np.all(np.asarray(jac2[240:]) == 0.0)
    np.testing.assert_allclose(np.asarray(blocks(jac2, bigger)), np.asarray(blocks(jac, problem)),
                               rtol=1e-6, atol=1e-6 * scale)


@pytest.mark.parametrize("samples, shape, wrap", [(1, MAP, "repeat"), (2, MAP, "repeat"), (1, (4, 3), "repeat"),
                                                  (2, (5, 6), "clamp")])
def test_neighbour_blocks_are_those_of_the_dense_matrix(capture, samples, shape, wrap):
    """The blocks of JᵀJ between neighbouring texels (`neighbour_blocks`), wrapped around the map,
    against the dense Jacobian: with 2 × 2 samples the taps of different samples pair up too."""
    obs = observations_from_capture(capture, pixel_samples=samples)
    keep = np.flatnonzero(np.asarray(obs.view_index) == 0)[: samples * samples * 150]
    obs = dataclasses.replace(obs, **{k: getattr(obs, k)[keep] for k in PIXEL_FIELDS})
    t = shape[0] * shape[1]
    layout = texel_layout(obs, shape, wrap)
    problem = dataclasses.replace(_problem(obs, capture), index=layout.index, weight=layout.weight,
                                  free=jnp.ones((t, 5)))
    x = jnp.asarray(np.random.default_rng(2).uniform(0.1, 0.9, (t, 5)), jnp.float32)
    _, jac, _ = jax.jit(linearize)(x, problem)
    dense = np.asarray(_dense_jacobian(x, problem), np.float64).reshape(-1, t * 5)
    jtj = dense.T @ dense
    got = np.asarray(jax.jit(neighbour_blocks, static_argnums=2)(jac, problem, shape))
    h, w = shape
    want = np.stack([[jtj[5 * s:5 * s + 5, 5 * u:5 * u + 5] for u in
                      (((s // w + di) % h) * w + (s % w + dj) % w for di, dj in NEIGHBOUR_OFFSETS)] for s in range(t)])
    scale = np.abs(jtj).max()
    assert np.abs(want).max() > 0.1 * scale  # the pixels couple neighbours strongly
    np.testing.assert_allclose(got, want, atol=1e-6 * scale)
    # these and the diagonal blocks hold all of JᵀJ at pixel centres; with samples, a pixel's taps
    # can lie two texels apart, and the blocks left out are small (here 7e-4 of the largest)
    near = np.zeros((t, t), bool)
    for s in range(t):
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                near[s, ((s // w + di) % h) * w + (s % w + dj) % w] = True
    blocks = np.abs(jtj).reshape(t, 5, t, 5).max(axis=(1, 3))
    assert blocks[~near].max() <= (1e-6 if samples == 1 else 1e-2) * scale
    if wrap == "clamp":  # no pixel reads across the edge: the wrapped neighbours' blocks are zero
        assert np.all(got[w - 1::w, 0] == 0.0) and np.all(got[(h - 1) * w:, 2] == 0.0)
    # the same blocks read from the stencil's assembly (`pbrfit.fitting.stencil`), and the diagonal ones
    gridded = with_stencil(dataclasses.replace(problem, grid=texel_grid(shape, t)))
    assert stencil_covers(gridded) and stencil_covers(gridded, shape)
    assert not stencil_covers(gridded, (2 * gridded.stencil.side - 2, 8))  # offsets that meet: through the pixels
    np.testing.assert_allclose(np.asarray(jax.jit(data_neighbour_blocks, static_argnums=2)(jac, gridded, shape)), want,
                               atol=1e-6 * scale)
    diagonal = np.stack([jtj[5 * s:5 * s + 5, 5 * s:5 * s + 5] for s in range(t)])
    for by_stencil in (True, False):
        np.testing.assert_allclose(np.asarray(jax.jit(data_blocks, static_argnums=2)(jac, gridded, by_stencil)),
                                   diagonal, atol=1e-6 * scale)


_FITS = {}


def _footprint_fit(capture):
    """The 2 × 2 fit of the module's capture, shared by the tests that compare with it."""
    if "samples" not in _FITS:
        _FITS["samples"] = fit(capture, resolution=MAP[0], pixel_samples=2)
    return _FITS["samples"]


def test_supersampled_capture_fitted_exactly_with_pixel_samples(capture, capture_dir):
    """Noiseless 2 × 2 supersampled images: pixel centres leave a bias in the maps, 2 × 2
    samples per pixel (the capture's own footprint) recover them."""
    truth = read_material(capture_dir / "truth")
    centre = fit(capture, resolution=MAP[0], pixel_samples=1)
    footprint = _footprint_fit(capture)
    assert footprint.report["pixel_samples"] == 2 and centre.report["pixel_samples"] == 1
    assert footprint.report["pixels"] <= centre.report["pixels"]
    got, was = map_rmse(truth, footprint), map_rmse(truth, centre)
    assert got["base_color"] < 2e-3 and got["metallic"] < 5e-3 and got["roughness"] < 1e-2, got
    assert was["roughness"] > 3 * got["roughness"] and was["base_color"] > 3 * got["base_color"], (was, got)
    assert footprint.report["final_loss"] < 0.01 * centre.report["final_loss"]
    # the per-view renders are per pixel: the images match the targets where the pixels are
    for img, tgt, msk in zip(footprint.images, footprint.targets, footprint.masks):
        assert msk.any() and np.abs(img[msk] - tgt[msk]).max() < 0.02


def test_estimated_noise_level_on_the_automatic_footprint(capture, capture_dir):
    """--noise-level estimated on a supersampled capture: the first fit keeps 2 × 2 samples, and
    the weighted second fit runs on them alone (no centres' steps, search or repair), from the
    first fit's maps, which it keeps as exact as the plain fit."""
    steps = []
    res = fit(capture, resolution=MAP[0], pixel_samples="auto", noise_level="estimated", progress=steps.append)
    assert res.report["footprint"]["selected"] == 2 and res.report["pixel_samples"] == 2
    weighted = [h for h in steps if h.get("weighted")]
    assert weighted and not any(h.get("footprint") or h.get("repair") for h in weighted), weighted
    assert res.report["noise_level"]["mode"] == "estimated"
    assert res.report["steps"] > res.report["noise_level"]["first_fit"]["steps"]
    got = map_rmse(read_material(capture_dir / "truth"), res)
    assert got["base_color"] < 2e-3 and got["metallic"] < 5e-3 and got["roughness"] < 1e-2, got


def test_pixel_samples_with_per_pixel_ibl(tmp_path, monkeypatch):
    """Per-pixel IBL integrals are computed for the samples and for the pixel centres the
    start runs on, in one pass, and each problem gets its own rows (what `fit` hands
    `fit_observations`; the sharded test fits samples with per-pixel rows)."""
    import pbrfit.fitting.api as fit_module
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.lighting.pixel_ibl import PixelIBLSettings, pixel_ibl
    from pbrfit.render.views import capture_environment

    synthesize(make_scene("sphere-env", seed=1, size=24, views=2, texture_size=MAP[0], env_width=32), tmp_path / "cap")
    capture = load_capture(tmp_path / "cap")
    settings = PixelIBLSettings(samples=16, levels=4)
    seen = {}

    class Handed(Exception):
        pass

    def spy(obs, options, **kwargs):
        seen.update(kwargs, obs=obs, options=options)
        raise Handed

    monkeypatch.setattr(fit_module, "fit_observations", spy)
    with pytest.raises(Handed):
        fit(capture, resolution=MAP[0], ibl="per_pixel", pixel_samples=2, pixel_ibl_settings=settings)
    assert seen["options"].pixel_samples == 2 and seen["model"].ibl == "per_pixel"
    env = capture_environment(capture)
    assert seen["obs"].samples == 4 and seen["centres"].samples == 1
    # one pass over the centres' rows, then the samples': the reference is that pass, split
    centres, samples = seen["centres"], seen["obs"]
    normal, view = (np.concatenate([np.asarray(getattr(o, name)) for o in (centres, samples)]) for name in ("normal", "view"))
    want = np.asarray(pixel_ibl(env, normal, view, seen["model"], settings).table)
    for want_rows, tables, obs in zip(np.split(want, [centres.num_rows]), (seen["centre_ibl"], seen["ibl"]),
                                      (centres, samples)):
        got = np.asarray(tables.table)
        assert got.shape == want_rows.shape and got.shape[0] == obs.num_rows
        # equal but for float32 rounding, which differs with the batch's shape and the CPU: a
        # sample direction on an environment texel's edge may round to its neighbour (seen: 6
        # of 22,032 values 7e-4 apart on one host); rows of two passes differ by the noise
        close = np.isclose(got, want_rows, rtol=1e-4, atol=1e-5)
        assert close.mean() > 0.999, close.mean()
        assert np.max(np.abs(got - want_rows) / (np.abs(want_rows) + 1e-2)) < 2e-3


def _same_fit(a, b):
    for name in ("base_color", "metallic", "roughness"):
        np.testing.assert_allclose(np.asarray(getattr(a.material, name)), np.asarray(getattr(b.material, name)),
                                   rtol=0, atol=1e-6, err_msg=name)
    np.testing.assert_array_equal(a.coverage, b.coverage)
    np.testing.assert_allclose(a.uncertainty, b.uncertainty, rtol=1e-3)
    assert a.report["pixels"] == b.report["pixels"] and a.report["pixel_samples"] == b.report["pixel_samples"]
    if jax.default_backend() == "cpu":
        assert a.report["steps"] == b.report["steps"] and a.report["levels"] == b.report["levels"]
    else:  # a GPU's reductions round differently in the two compiles: tolerance stops move by a few steps
        assert [h["resolution"] for h in a.report["levels"]] == [h["resolution"] for h in b.report["levels"]]


def test_auto_footprint_keeps_samples_for_a_supersampled_capture(capture):
    """sRGB images: ``"auto"`` fits 2 × 2 samples and pixel centres from the same start and keeps
    the samples here, whose images match (the capture is 2 × 2 supersampled); the kept fit is
    the 2 × 2 fit itself."""
    auto = fit(capture, resolution=MAP[0])
    foot = auto.report["footprint"]
    assert foot["selected"] == 2 and foot["pixels"] == auto.report["pixels"] and not foot["stopped_early"]
    assert foot["energies"]["2"] < 0.01 * foot["energies"]["1"], foot
    _same_fit(auto, _footprint_fit(capture))


def test_the_repair_searches_a_samples_fit_at_pixel_centres(tmp_path):
    """A noisy 2 × 2 supersampled sRGB capture: ``"auto"`` keeps the samples, and the repair's
    outlier pass searches at pixel centres, as the fit's own search does (with its program),
    its steps and its judging on the samples."""
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize

    synthesize(make_scene("plane-flash", seed=3, size=32, views=4, texture_size=MAP[0]), tmp_path / "cap")
    res = fit(load_capture(tmp_path / "cap"), resolution=MAP[0])
    assert res.report["footprint"]["selected"] == 2 and res.report["pixel_samples"] == 2
    searched = [p for p in res.report["repair"]["passes"] if "searched_samples" in p]
    assert searched and all(p["searched_samples"] == 1 for p in searched), res.report["repair"]


def test_auto_footprint_keeps_centres_for_a_capture_rendered_at_centres(tmp_path):
    """A plane rendered at pixel centres into 16-bit sRGB PNGs, its edges in view (pixels there
    that some sample misses are used by the centres only): ``"auto"`` keeps the centres' fit,
    the very fit of ``pixel_samples=1`` (texels only those pixels read included), and reports
    both energies."""
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize

    synthesize(make_scene("peer-plane", seed=3, size=32, views=4, texture_size=MAP[0], image_format="png16"),
               tmp_path / "cap")
    capture = load_capture(tmp_path / "cap")
    auto = fit(capture, resolution=MAP[0])
    centre = fit(capture, resolution=MAP[0], pixel_samples=1)
    foot = auto.report["footprint"]
    assert foot["selected"] == 1 and foot["energies"]["1"] < 0.01 * foot["energies"]["2"], foot
    # the samples stopped after their first steps, which fitted worse than the centres' whole finish
    assert foot["stopped_early"] and foot["steps"]["2"] <= SEARCH_AFTER + PROBE_STEPS, foot
    assert foot["pixels"] < centre.report["pixels"]  # the edges' pixels are left out of the comparison
    assert "footprint" not in centre.report
    _same_fit(auto, centre)
    assert map_rmse(read_material(tmp_path / "cap" / "truth"), auto)["roughness"] < 1e-3


def test_texels_only_centres_read_are_fitted_when_centres_are_kept(tmp_path):
    """Samples that miss the mesh drop their pixel, so the centres can see texels no sample row
    reads. Here the sample rows of every pixel outside the map's middle half are dropped: when
    the centres' fit is kept, the texels only centres read are fitted and observed as in a fit
    of centres alone."""
    import equinox as eqx

    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fitting.api import fit_observations
    from pbrfit.fitting.observations import PIXEL_FIELDS

    synthesize(make_scene("peer-plane", seed=4, size=32, views=4, texture_size=MAP[0], image_format="png16"),
               tmp_path / "cap")
    capture = load_capture(tmp_path / "cap")
    model = model_for_capture(capture)
    centres = observations_from_capture(capture)
    samples = observations_from_capture(capture, pixel_samples=2)
    u = np.asarray(samples.pixel_rows(samples.uv))[:, 0] % 1.0
    keep = np.flatnonzero((u >= 0.25) & (u <= 0.75))  # textures repeat: column 0 is read from both sides
    rows = jnp.asarray((keep[:, None] * samples.samples + np.arange(samples.samples)).ravel(), jnp.int32)
    samples = eqx.tree_at(lambda o: tuple(getattr(o, n) for n in PIXEL_FIELDS), samples,
                          tuple(getattr(samples, n)[rows] for n in PIXEL_FIELDS))
    auto = fit_observations(samples, model=model, resolution=MAP[0], centres=centres, select_footprint=True)
    alone = fit_observations(centres, model=model, resolution=MAP[0])
    assert auto.report["footprint"]["selected"] == 1
    sampled = coverage_counts(texel_layout(samples, MAP), samples.samples)
    assert (sampled[:, 0] == 0).all() and (alone.coverage[:, 0] > 0).all()  # column 0: centres only
    _same_fit(auto, alone)


def test_auto_footprint_with_an_optimistix_solver_and_a_uniform_material(capture):
    """The choice also works where the solver returns no linearisation (optimistix) and for
    one uniform material: the kept fit is the one of lower energy."""
    res = fit(capture, maps="none", solver="lm", max_steps=5)
    foot = res.report["footprint"]
    e = {int(k): v for k, v in foot["energies"].items()}
    assert set(e) == {1, 2} and all(np.isfinite(v) and v > 0 for v in e.values())
    assert foot["selected"] == min(e, key=e.get) == res.report["pixel_samples"]
    assert not foot["stopped_early"]  # the early stop is the structured solver's
    assert res.report["resolution"] == [1, 1] and np.isfinite(res.report["final_loss"])


def test_select_footprint_needs_samples_and_centres(capture):
    from pbrfit.fitting.api import fit_observations

    obs = observations_from_capture(capture)
    with pytest.raises(ValueError, match="select_footprint"):
        fit_observations(obs, model=model_for_capture(capture), resolution=MAP[0], select_footprint=True)


def test_footprint_choice_by_image_kind(capture):
    """``"auto"`` tries 2 × 2 samples for display-referred images only; an integer is taken as
    given; precomputed views hold centres."""
    from pbrfit.fitting.stages.footprint import AUTO_PIXEL_SAMPLES, footprint_choice, probes_footprint

    linear = dataclasses.replace(capture, frames=[dataclasses.replace(f, color_space="linear") for f in capture.frames],
                                 color_space="linear")
    assert footprint_choice(capture) == (AUTO_PIXEL_SAMPLES, True, None)
    assert footprint_choice(linear) == (1, False, None)
    assert footprint_choice(dataclasses.replace(linear, tonemap="reinhard")) == (AUTO_PIXEL_SAMPLES, True, None)
    assert footprint_choice(capture, views=[object()]) == (1, False, None)
    # linear images: a centre fit, tested for a box footprint (`probes_footprint`) unless asked otherwise
    assert probes_footprint(linear) and not probes_footprint(capture) and not probes_footprint(linear, 1)
    assert not probes_footprint(linear, views=[object()])
    assert footprint_choice(capture, 3) == (3, False, None) and footprint_choice(linear, 1) == (1, False, None)
    with pytest.raises(ValueError, match="auto"):
        footprint_choice(capture, "many")


def test_auto_footprint_skips_the_samples_on_a_large_capture(capture, capture_dir, monkeypatch):
    """Beyond `AUTO_MAX_PIXELS` image pixels the automatic choice keeps to pixel centres (four
    times the rows would not pay), and the report says so. (The fit is given the capture's
    folder: `pbrfit.fit` reads it.)"""
    import pbrfit.fitting.stages.footprint as fit_module

    pixels = sum(f.image.shape[0] * f.image.shape[1] for f in capture.frames)
    monkeypatch.setattr(fit_module, "AUTO_MAX_PIXELS", pixels - 1)
    n, select, skipped = fit_module.footprint_choice(capture)
    assert (n, select) == (1, False) and f"{pixels:,} image pixels > AUTO_MAX_PIXELS" in skipped
    assert fit_module.footprint_choice(capture, 2) == (2, False, None)  # asked for: no limit
    res = fit(str(capture_dir), maps="none", max_steps=5)
    assert res.report["pixel_samples"] == 1 and "energies" not in res.report["footprint"]
    assert f"{pixels:,} image pixels > AUTO_MAX_PIXELS" in res.report["footprint"]["skipped"]
    monkeypatch.setattr(fit_module, "AUTO_MAX_PIXELS", pixels)
    assert fit_module.footprint_choice(capture) == (fit_module.AUTO_PIXEL_SAMPLES, True, None)


def _smooth_views(n: int = 24, k: int = 4):
    """A smooth image at pixel centres and the box average of each pixel (k × k sub-pixel samples)."""
    def f(y, x):
        return 0.5 + 0.4 * np.sin(0.35 * x + 0.2 * y) * np.cos(0.3 * y)

    centre = (np.arange(n) + 0.5)[:, None], (np.arange(n) + 0.5)[None, :]
    sub = (np.arange(n * k) + 0.5) / k
    box = f(sub[:, None], sub[None, :]).reshape(n, k, n, k).mean(axis=(1, 3))
    return np.repeat(f(*centre)[..., None], 3, -1), np.repeat(box[..., None], 3, -1)


def test_footprint_evidence_sees_a_box_average():
    """The centres' residuals follow the render's Laplacian / 24 with slope about 1 where the images
    are box averages, and scatter about 0 where they hold the centres plus noise; all-zero
    residuals are no evidence at all."""
    from pbrfit.fitting.stages.footprint import BOX_SLOPE, box_plausible, footprint_evidence

    render, box = _smooth_views()
    mask = np.ones(render.shape[:2], bool)
    mask[:3] = False  # pixels outside the mask (and their neighbours) are not read
    on_box = footprint_evidence([render], [box], [mask])
    assert 0.8 < on_box["slope"] < 1.2 and box_plausible(on_box), on_box
    assert on_box["values"] == 3 * (render.shape[0] - 5) * (render.shape[1] - 2)
    noisy = render + np.random.default_rng(0).normal(0.0, 1e-3, render.shape)
    on_centres = footprint_evidence([render], [noisy], [mask])
    assert abs(on_centres["slope"]) < BOX_SLOPE and not box_plausible(on_centres), on_centres
    exact = footprint_evidence([render], [render], [mask])
    assert exact["slope"] == 0.0 and exact["z"] == 0.0 and not box_plausible(exact)


def test_auto_footprint_tests_linear_images_before_fitting_both(tmp_path):
    """Linear EXR images: ``"auto"`` fits pixel centres, then both footprints only where the
    centres' residuals show a box's blur: on a 2 × 2 supersampled capture it keeps the samples
    (3 × 3 of them: `AUTO_LINEAR_PIXEL_SAMPLES`), the centres' fit counted as "footprint_probe"
    time. (A capture rendered at centres keeps its centres' fit alone:
    tests/cli/test_cli_fit.py::test_fit_writes_the_spec_output.)"""
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fitting.stages.footprint import AUTO_LINEAR_PIXEL_SAMPLES

    synthesize(make_scene("plane-flash", seed=3, size=24, views=3, texture_size=MAP[0], noise=0.0,
                          image_format="exr", supersample=2), tmp_path / "box")
    box = fit(load_capture(tmp_path / "box"), resolution=MAP[0], search=False, repair=False,
              uniform_check=False).report
    foot = box["footprint"]
    assert foot["selected"] == AUTO_LINEAR_PIXEL_SAMPLES == box["pixel_samples"] == 3, foot
    assert foot["evidence"]["slope"] > 0.1, foot
    # (3 × 3 samples are 5/36 of the blur off a 2 × 2 box where the centres are 3/4 off: about 1/30 of the
    # energy for smooth images, more at this capture's highlights; 2 × 2 samples would be exact)
    assert foot["energies"]["3"] < 0.25 * foot["energies"]["1"]
    assert box["times"]["footprint_probe"] > 0.0
