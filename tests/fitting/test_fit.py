"""Fitting on tiny hand-built scenes: a plane under point lights seen by a few cameras.

Geometry is analytic (no ray casting, no files), so these test the fit alone. Shapes are shared
between tests so the solver compiles once per configuration.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from pbrfit.physics.color import encode
import pbrfit.fitting.api
import pbrfit.fitting.passes
import pbrfit.fitting.initialisation
import pbrfit.fitting.objective
import pbrfit.fitting.stages.repair
import pbrfit.fitting.runner
import pbrfit.fitting.result
import pbrfit.fitting.stages.selection
import pbrfit.fitting.solvers.structured
from pbrfit.fitting.api import SOLVERS, default_resolution, fit_observations, map_rmse, schedule
from pbrfit.fitting.options import fit_arguments
from pbrfit.fitting.options import LOSS_SCALE
from pbrfit.fitting.passes import COARSE_STEPS, RELEASED_STEPS, SEARCH_AFTER, SETTLE_STEPS
from pbrfit.fitting.stages.pipeline import TURNED_OFF
from pbrfit.fitting.initialisation import (SEARCH_ROUGHNESS_RATIO, classes_share_no_pixel, coordinate_search,
                                          grid_initialise, parity_classes)
from pbrfit.physics.lights import point_light
from pbrfit.physics.material import Material
from pbrfit.physics.model import Model
from pbrfit.fitting.observations import (PIXEL_FIELDS, coverage_counts, neighbour_pairs, observations_from_views,
                                        texel_layout)
from pbrfit.fitting.stencil import with_stencil
from pbrfit.fitting.parameters import LOWER, UPPER, from_sine, to_sine
from pbrfit.fitting.stages.repair import REPAIR_PROGRESS, SEARCH_COMPILE_COST, search_problem
from pbrfit.fitting.sharding import halving_sizes, moving_pixels, take_pixels, take_texels, texel_program, texel_rows
from pbrfit.render.shade import ViewInputs, light_arrays, radiance_view
from pbrfit.fitting.objective import Problem, objective, texel_grid
from pbrfit.fitting.solvers.structured import StructuredLM, solve
from pbrfit.fitting.normal_matrix import normal_blocks
from pbrfit.xla import FAST_COMPILE

RES = 24  # pixels per view side


def _look_at(eye):
    eye = np.asarray(eye, float)
    f = -eye / np.linalg.norm(eye)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    return np.stack([right, up, -f], 1)


def _views(n_views=4, extent=1.0, res=RES):
    """Views of the plane z = 0, |x|, |y| < extent (uv = (x, y)/2/extent + 1/2), four lights."""
    lights = [point_light((2.0 * math.cos(a), 2.0 * math.sin(a), 1.6), (1, 1, 1), 5.0)
              for a in np.linspace(0.3, 2 * math.pi + 0.3, 4, endpoint=False)]
    views = []
    f = 0.5 * res / math.tan(math.radians(22.5))
    for k in range(n_views):
        az = 2 * math.pi * k / max(n_views, 1) + 0.2
        el = math.radians(55 + 12 * (k % 2))
        eye = 2.9 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        rot = _look_at(eye)
        j, i = np.meshgrid(np.arange(res) + 0.5, np.arange(res) + 0.5)
        d = np.stack([(j - res / 2) / f, -(i - res / 2) / f, -np.ones_like(j)], -1) @ rot.T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        t = -eye[2] / d[..., 2]
        pos = eye + t[..., None] * d
        hit = (np.abs(pos[..., 0]) < 0.999) & (np.abs(pos[..., 1]) < 0.999)
        flat = np.flatnonzero(hit.reshape(-1))
        p = pos.reshape(-1, 3)[flat]
        v = eye - p
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        ll, lr = light_arrays(lights, p)
        n = len(flat)
        views.append(ViewInputs(
            pixel=jnp.asarray(flat, jnp.int32), uv=jnp.asarray(p[:, :2] / (2 * extent) + 0.5, jnp.float32),
            normal=jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (n, 1)),
            tangent=jnp.tile(jnp.array([[1.0, 0.0, 0.0, 1.0]]), (n, 1)),
            view=jnp.asarray(v, jnp.float32), light_l=ll, light_radiance=lr, shape=(res, res)))
    return views


def _images(views, material, model=Model(), color_space="linear"):
    out = []
    for vi in views:
        img = np.zeros((vi.shape[0] * vi.shape[1], 3), np.float32)
        img[np.asarray(vi.pixel)] = np.asarray(encode(radiance_view(vi, material, model), 0.0, "none", color_space))
        out.append(img.reshape(vi.shape + (3,)))
    return out


VIEWS = _views()


def _checker(n=8):
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    c = ((i // 2 + j // 2) % 2).astype(np.float32)[..., None]
    base = np.where(c > 0, np.array([0.7, 0.3, 0.2]), np.array([0.2, 0.5, 0.6])).astype(np.float32)
    return Material(jnp.asarray(base), jnp.zeros((n, n, 1)), jnp.asarray(0.35 + 0.1 * c))


def test_sine_storage_reaches_bounds_and_inverts():
    x = np.array([[0.0, 0.3, 1.0, 0.5, LOWER[4]], [1.0, 0.0, 0.2, 1.0, 1.0]], np.float32)
    np.testing.assert_allclose(np.asarray(from_sine(to_sine(x))), x, atol=1e-6)
    assert np.all(np.asarray(from_sine(jnp.full((5,), 100.0))) <= UPPER)
    with jax.enable_x64(True):  # the bounds in float64 too: reached exactly (they were float32's)
        bounds = jnp.asarray(np.stack([LOWER, UPPER]), jnp.float64)
        back = from_sine(to_sine(bounds))
        assert back.dtype == jnp.float64 and np.array_equal(np.asarray(back), np.asarray(bounds))


def test_normal_slopes_round_trip_and_bounds():
    from pbrfit.fitting.parameters import NORMAL_SLOPE_MAX, channel_mask, lower, normal_from_slopes, slopes_from_normal, upper

    s = np.array([[0.0, 0.0], [0.3, -0.2], [-2.0, 1.5], [NORMAL_SLOPE_MAX, -NORMAL_SLOPE_MAX]], np.float32)
    n = np.asarray(normal_from_slopes(s))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(n[0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(n[1], np.array([0.3, -0.2, 1.0]) / np.sqrt(1.13), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(slopes_from_normal(n)), s, rtol=1e-5, atol=1e-6)
    # a normal at the horizon maps to the largest slope, not to infinity
    assert np.all(np.abs(np.asarray(slopes_from_normal(jnp.array([1.0, 0.0, 0.0])))) <= NORMAL_SLOPE_MAX)
    # sine storage covers the slope channels too
    x = np.concatenate([[0.2, 0.4, 0.6, 1.0, 0.5], s[2]]).astype(np.float32)
    np.testing.assert_allclose(np.asarray(from_sine(to_sine(x))), x, atol=1e-5)
    assert np.all(np.asarray(from_sine(jnp.full((7,), 100.0))) <= upper(7))
    assert lower(7)[5] == -NORMAL_SLOPE_MAX and channel_mask(("roughness", "normal")).tolist() == [0, 0, 0, 0, 1, 1, 1]


@pytest.mark.parametrize("truth", [((0.6, 0.35, 0.2), 0.0, 0.35), ((0.9, 0.7, 0.3), 1.0, 0.25),
                                   ((0.3, 0.5, 0.7), 0.4, 0.6)])
def test_uniform_material_recovered(truth):
    base, metal, rough = truth
    obs = observations_from_views(VIEWS, _images(VIEWS, Material.uniform(base, metal, rough)))
    res = fit_observations(obs, maps="none", max_steps=60, rtol=0.0, atol=1e-7)
    got = np.concatenate([np.asarray(res.material.base_color).ravel(), np.asarray(res.material.metallic).ravel(),
                          np.asarray(res.material.roughness).ravel()])
    np.testing.assert_allclose(got, [*base, metal, rough], atol=1e-4)
    assert res.material.resolution == (1, 1) and res.uncertainty.shape == (1, 1, 5)
    assert res.report["solver"] == "structured" and len(res.report["psnr"]) == len(VIEWS)


def test_fit_observations_takes_the_model_fields_the_options_change():
    """``model={"diffuse": "burley"}`` in the options shades with those fields changed in the
    default model (the command line's ``--model``), as the report records; the images were
    rendered with Lambert, so the fit does not match them exactly."""
    obs = observations_from_views(VIEWS, _images(VIEWS, Material.uniform((0.6, 0.35, 0.2), 0.0, 0.35)))
    burley = fit_observations(obs, maps="none", max_steps=20, model={"diffuse": "burley"})
    lambert = fit_observations(obs, maps="none", max_steps=20)
    assert burley.report["model"] == Model(diffuse="burley").describe()
    assert lambert.report["model"]["diffuse"] == "lambert"
    assert burley.report["final_loss"] > 1e3 * lambert.report["final_loss"]


def test_default_resolution_has_no_more_texels_than_pixels():
    """Views that see a speck of the texture (here 1e-5 of its width) ask for the finest map
    their footprint resolves (2048, almost all unseen); the default stops at one texel per pixel."""
    views = _views(n_views=2, extent=1e5)
    obs = observations_from_views(views, [np.zeros((RES, RES, 3), np.float32)] * 2)
    assert default_resolution(obs) == 2 ** int(math.log2(math.sqrt(obs.num_pixels))) <= 32


def test_default_resolution_follows_the_pixel_footprint():
    """Where the views have pixels to spare, the footprint decides: full-frame views whose pixels
    step exactly 1/24 in u and in v (the median footprint) give texels at least one pixel wide up
    to 16² (24 ≥ 16, < 32). Sixteen such views (9216 pixels) would give each texel of a 32² map 9
    observations (OBSERVATIONS_PER_TEXEL is 8) and allow up to 64² texels (one per pixel): only
    the footprint holds the map at 16."""
    side = 24
    i, j = np.divmod(np.arange(side * side), side)
    uv = (np.stack([j, i], -1) + 0.5) / side
    n = side * side
    view = ViewInputs(pixel=jnp.arange(n, dtype=jnp.int32), uv=jnp.asarray(uv, jnp.float32),
                      normal=jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (n, 1)),
                      tangent=jnp.tile(jnp.array([[1.0, 0.0, 0.0, 1.0]]), (n, 1)),
                      view=jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (n, 1)),
                      light_l=jnp.tile(jnp.array([[[0.0, 0.0, 1.0]]]), (n, 1, 1)),
                      light_radiance=jnp.zeros((n, 1, 3)), shape=(side, side))
    obs = observations_from_views([view] * 16, [np.zeros((side, side, 3), np.float32)] * 16)
    assert obs.num_pixels == 9216 >= 8 * 32 * 32
    assert default_resolution(obs) == 16


def test_maps_recovered_on_small_scene():
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    # the pixels' median footprint (0.050 uv wide) would allow 16, but the 4 views' 1444 pixels
    # over the 256 texels of a 16² map are 5.6 each, below OBSERVATIONS_PER_TEXEL (8): 8
    assert default_resolution(obs) == 8
    res = fit_observations(obs, resolution=8, max_steps=40)
    err = map_rmse(truth, res)
    assert err["base_color"] < 0.01 and err["roughness"] < 0.03 and err["metallic"] < 0.02, err
    assert np.all(res.coverage > 0)
    # noiseless and exact: the outlier pass flags the checker's edges, but no cluster's pixels
    # misfit by its evidence threshold, so none could be kept, and it takes no step
    (outliers,) = res.report["repair"]["passes"]
    assert outliers["kind"] == "outliers" and outliers["flagged"] > 0, outliers
    assert outliers["steps"] == 0 and outliers["skipped"] and not outliers["kept"], outliers


def test_a_second_fit_of_the_same_shapes_compiles_nothing():
    """A script's second fit of the same shapes and settings runs on the first's programs (JAX
    keeps them in memory), without lowering any (which even a persistent cache's hit does first),
    also when it reports progress: the solver keeps its losses in its state and they are reported
    after each solve, so its program holds no host callback, which would be another at each fit."""
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    reported = []
    first = fit_observations(obs, resolution=8, max_steps=16, progress=reported.append)
    losses = [entry["loss"] for entry in reported if "loss" in entry]
    # every step reported, once: the solve's steps and the stages' (their steps count apart)
    assert len(losses) >= first.report["steps"] + 1 and losses[-1] == pytest.approx(first.report["final_loss"], rel=1e-3)
    lowered = []
    counting = [True]

    def count(event, seconds, **kwargs):
        if counting[0] and event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            lowered.append(seconds)

    jax.monitoring.register_event_duration_secs_listener(count)
    try:
        second = fit_observations(obs, resolution=8, max_steps=16, progress=reported.append)
    finally:
        counting[0] = False
    assert lowered == []
    np.testing.assert_array_equal(np.asarray(second.material.base_color), np.asarray(first.material.base_color))


def test_progress_names_each_stage_as_it_begins():
    """Between the solver's runs, whose steps are reported as each run ends, the progress callback
    hears which stage begins, with the level and resolution: the grid start, the solve, the
    search, the solve again, then each stage after the solve that runs, in the report's order."""
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    reported = []
    res = fit_observations(obs, resolution=8, max_steps=16, progress=reported.append)
    stages = [entry["stage"] for entry in reported if "stage" in entry]
    ran = [s["name"].replace("_", " ") for s in res.report["stages"] if s["ran"]]
    assert ran and stages[:4] == ["grid start", "solving", "search", "solving"], stages
    assert stages[4:4 + len(ran)] == ran and stages[4 + len(ran):] in ([], ["standard errors"]), stages
    assert all(entry["level"] == 0 and tuple(entry["resolution"]) == (8, 8) for entry in reported)
    first_step = next(i for i, entry in enumerate(reported) if "loss" in entry)
    assert [entry.get("stage") for entry in reported[:first_step]] == ["grid start", "solving"]
    # each step with its solve's budget: the steps before the search (SEARCH_AFTER), then the rest
    # of max_steps, then each stage's solves (the hold's, the repair's, the uniform check's)
    steps = [entry for entry in reported if "loss" in entry]
    assert all(0 <= entry["step"] <= entry["budget"] for entry in steps), steps
    budgets = [entry["budget"] for entry in steps]
    assert budgets[0] == SEARCH_AFTER and 16 - SEARCH_AFTER in budgets, budgets


def test_coarse_to_fine_runs_its_levels_and_recovers_the_maps():
    """coarse_to_fine=True runs `schedule`'s levels, a uniform material and then the 8 × 8 maps
    (8 has no level between: 8 / LEVEL_FACTOR is below 4), each with steps of its own in the
    report, and ends where the direct fit does (`test_maps_recovered_on_small_scene`)."""
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    res = fit_observations(obs, resolution=8, max_steps=40, coarse_to_fine=True)
    levels = res.report["levels"]
    assert [h["resolution"] for h in levels] == [[1, 1], [8, 8]] == [list(s) for s in schedule((8, 8))], levels
    assert all(h["steps"] > 0 for h in levels), levels
    assert res.material.resolution == (8, 8)
    err = map_rmse(truth, res)
    assert err["base_color"] < 0.01 and err["roughness"] < 0.03 and err["metallic"] < 0.02, err


def test_unseen_texels_flagged_and_left_at_prior():
    truth = _checker()
    half = [_views(2, extent=2.0)[k] for k in range(2)]  # the plane covers only the centre of uv
    obs = observations_from_views(half, _images(half, Material(truth.base_color, truth.metallic, truth.roughness)))
    res = fit_observations(obs, resolution=8, max_steps=5, search=False, repair=False, uniform_check=False)
    unseen = res.coverage == 0
    assert unseen.any() and (~unseen).any()
    assert np.all(np.isinf(res.uncertainty[unseen]))
    np.testing.assert_allclose(np.asarray(res.material.roughness)[unseen][:, 0], 0.5)
    assert np.all(np.isfinite(res.uncertainty[~unseen]))


def test_roughness_the_images_do_not_constrain_is_held_at_the_prior(monkeypatch):
    """`pbrfit.fitting.stages.unconstrained`: the texels whose roughness σ exceeds the threshold get 0.5 and a
    re-fit of their base colour; every other texel keeps the value the solve gave it."""
    import pbrfit.fitting.result
    import pbrfit.fitting.stages.pipeline
    import pbrfit.fitting.stages.unconstrained
    from pbrfit.fitting.result import texel_standard_errors
    from pbrfit.fitting.stages.unconstrained import ROUGHNESS, hold_skipped

    truth = _checker()
    rng = np.random.default_rng(5)
    imgs = [i + rng.normal(0, 0.02, i.shape).astype(np.float32) for i in _images(VIEWS, truth)]
    obs = observations_from_views(VIEWS, imgs)
    free = fit_observations(obs, resolution=8, max_steps=20, unconstrained_sigma=math.inf)
    assert free.report["unconstrained"] == dict(skipped=TURNED_OFF)
    s = free.uncertainty[..., ROUGHNESS]
    threshold = float(np.median(s[np.isfinite(s)]))  # half the texels count as unconstrained here
    res = fit_observations(obs, resolution=8, max_steps=20, unconstrained_sigma=threshold)
    report = res.report["unconstrained"]
    flagged = np.isfinite(s) & (s > threshold)  # σ at the solve's values, as the hold computes it
    x = lambda r: np.concatenate([np.asarray(r.material.base_color), np.asarray(r.material.metallic),  # noqa: E731
                                  np.asarray(r.material.roughness)], -1)
    held = flagged & (x(res)[..., ROUGHNESS] == 0.5)  # the rest the images constrain at 0.5: left as fitted
    assert report["texels"] == int(held.sum()) > 0 and report["threshold"] == threshold
    assert report["texels"] + report["constrained_at_prior"] == int(flagged.sum())
    assert report["steps"] > 0 and res.report["steps"] == free.report["steps"] + report["steps"]
    np.testing.assert_array_equal(x(res)[~held], x(free)[~held])  # the others keep their values
    assert not np.array_equal(x(res)[held][:, :3], x(free)[held][:, :3])  # the held texels' colour re-fitted
    # their σ: what the images give at 0.5, not the 0 of a channel the caller holds
    assert np.all(np.isfinite(res.uncertainty[..., ROUGHNESS][held]) & (res.uncertainty[..., ROUGHNESS][held] > 0))
    assert report["energy_after"] >= report["energy_before"] * (1 - 1e-6)  # held off the optimum
    # the result reads the hold's last standard errors, taken at its x, instead of computing them
    # again: as many as without them, and one computation fewer
    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return texel_standard_errors(*args, **kwargs)

    monkeypatch.setattr(pbrfit.fitting.stages.unconstrained, "texel_standard_errors", counted)
    monkeypatch.setattr(pbrfit.fitting.result, "texel_standard_errors", counted)
    again = fit_observations(obs, resolution=8, max_steps=20, unconstrained_sigma=threshold)
    reused = len(calls)
    run_hold = pbrfit.fitting.stages.pipeline.run_hold
    monkeypatch.setattr(pbrfit.fitting.stages.pipeline, "run_hold", lambda *a: run_hold(*a)[:4] + (None,))
    calls.clear()
    fresh = fit_observations(obs, resolution=8, max_steps=20, unconstrained_sigma=threshold)
    assert reused == len(calls) - 1, (reused, len(calls))
    np.testing.assert_array_equal(x(again), x(fresh))
    np.testing.assert_allclose(again.uncertainty, fresh.uncertainty, rtol=1e-5)
    monkeypatch.undo()
    # with base colour held by the caller there is nothing to re-fit: the roughness alone is held
    only = dict(resolution=8, max_steps=20, fit=("roughness",),
                fixed={"base_color": truth.base_color, "metallic": truth.metallic})
    s_only = fit_observations(obs, **only, unconstrained_sigma=math.inf).uncertainty[..., ROUGHNESS]
    threshold = float(np.median(s_only[np.isfinite(s_only)]))
    held_only = fit_observations(obs, **only, unconstrained_sigma=threshold)
    report = held_only.report["unconstrained"]
    assert report["texels"] > 0 and report["steps"] == 0, report
    assert int(np.sum(np.asarray(held_only.material.roughness) == 0.5)) == report["texels"]
    channels = np.ones(5, np.float32)
    assert hold_skipped("lm", 0.0, (8, 8), channels, {}) == "needs the structured solver"
    assert hold_skipped("structured", 0.1, (8, 8), channels, {}) == "the smoothness prior already ties the texels together"
    assert hold_skipped("structured", 0.0, (1, 1), channels, {}) == "a uniform material"
    assert hold_skipped("structured", 0.0, (8, 8), channels, {ROUGHNESS: 0.3}) == "roughness is one value (uniform check)"
    assert hold_skipped("structured", 0.0, (8, 8), np.array([1, 1, 1, 1, 0], np.float32), {}) == "roughness is not fitted"
    assert hold_skipped("structured", 0.0, (8, 8), channels, {3: 0.0}) is None


def test_uncertainty_grows_when_views_are_removed():
    truth = _checker()
    rng = np.random.default_rng(0)
    imgs = [i + rng.normal(0, 0.01, i.shape).astype(np.float32) for i in _images(VIEWS, truth)]
    obs = observations_from_views(VIEWS, imgs)
    full = fit_observations(obs, maps="none", fit=("base_color", "roughness"), max_steps=30)
    fewer = fit_observations(obs.select_views([0]), maps="none", fit=("base_color", "roughness"), max_steps=30)
    assert np.all(fewer.uncertainty[..., [0, 1, 2, 4]] > full.uncertainty[..., [0, 1, 2, 4]])
    assert np.all(full.uncertainty[..., 3] == 0)  # metallic held fixed


def test_uncertainty_window_widens_the_per_texel_errors():
    """The default uncertainty frees each texel's 3 × 3 window (`pbrfit.fitting.uncertainty`): the same
    maps, errors at least the per-texel blocks' and clearly wider where neighbours share pixels."""
    truth = _checker()
    rng = np.random.default_rng(3)
    imgs = [i + rng.normal(0, 0.01, i.shape).astype(np.float32) for i in _images(VIEWS, truth)]
    obs = observations_from_views(VIEWS, imgs)
    fits = {r: fit_observations(obs, resolution=8, max_steps=20, uncertainty_radius=r) for r in (0, 1)}
    for r, f in fits.items():
        assert f.report["uncertainty"] == dict(radius=r, window=[2 * r + 1] * 2)
    np.testing.assert_array_equal(np.asarray(fits[0].material.base_color), np.asarray(fits[1].material.base_color))
    seen = fits[0].coverage > 0
    own, window = fits[0].uncertainty[seen][:, :3], fits[1].uncertainty[seen][:, :3]
    assert np.all(window >= own) and np.median(window / own) > 1.05
    with pytest.raises(ValueError, match="uncertainty_radius"):
        fit_observations(obs, resolution=8, uncertainty_radius=4)


def test_uncertainty_matches_the_dense_window_inverse():
    """The size of the reported errors, end to end: σ̂ = sqrt(2 E / (n - p)) from the pixels'
    residuals, and each texel's σ = σ̂ sqrt(diag((JᵀJ)_W⁻¹)) at its channels, with (JᵀJ)_W the
    dense Gauss-Newton matrix (jax.jacfwd of the pixel residuals at the fitted maps) restricted to
    the texel's 3 × 3 window, wrapped around the map (`pbrfit.fitting.uncertainty`: the window's other
    texels free, those beyond held), widened by the sandwich's excess over σ̂² where there is one.
    Metallic is held at 0 and the uniform check is off, so no channel is pinned or made one value:
    every fitted σ is a window's. (One sample per pixel: a
    pixel reads a 2 × 2 block of texels, so the diagonal and neighbour blocks hold all of the
    window's matrix, and the two agree to float32 round-off and the window's 1e-6 ridge.)"""
    truth = _checker()
    obs = _noisy_checker_obs(truth, seed=3)
    blocks = pbrfit.fitting.runner._data_blocks.variants[1]  # (the program behind jitted_normal_blocks, small problems)
    blocks.clear_cache()
    res = fit_observations(obs, resolution=8, fixed={"metallic": 0}, uniform_check=False, max_steps=20)
    assert res.report["fitted"] == ["base_r", "base_g", "base_b", "roughness"] and np.all(res.coverage > 0)
    # the sandwich's meat goes through the Jacobians' own program (placed as they are): one compile
    assert blocks._cache_size() == 1
    problem = dataclasses.replace(_texel_problem(truth), obs=obs)
    x = np.asarray(_stack(res.material))
    r = np.asarray(jax.jit(pbrfit.fitting.objective.pixel_residuals)(jnp.asarray(x), problem), np.float64)
    jac = np.asarray(_dense_jacobian(jnp.asarray(x), problem), np.float64)
    fitted = [0, 1, 2, 4]
    jac = jac.reshape(-1, 64, 5)[:, :, fitted].reshape(len(r.ravel()), -1)  # the metallic columns held
    k = len(fitted)
    sigma2 = np.sum(r * r) / (r.size - 64 * k)
    np.testing.assert_allclose(res.report["residual_sigma"], np.sqrt(sigma2), rtol=1e-3)
    h = jac.T @ jac
    got = np.asarray(res.uncertainty).reshape(64, 5)
    assert np.all(got[:, 3] == 0)  # held
    want = np.empty((64, k))
    for s in range(64):
        i, j = divmod(s, 8)
        window = [((i + di) % 8) * 8 + (j + dj) % 8 for di in (-1, 0, 1) for dj in (-1, 0, 1)]
        cols = np.concatenate([np.arange(u * k, (u + 1) * k) for u in window])
        own = window.index(s)
        want[s] = np.sqrt(sigma2 * np.diag(np.linalg.inv(h[np.ix_(cols, cols)]))[own * k:(own + 1) * k])
    # widened where the texel's own pixels show more variance than σ̂² (the sandwich of its block:
    # `pbrfit.fitting.result.misfit_ratios`), from the dense Jacobian: M_t = Σ_p g_pt g_ptᵀ with
    # g_pt = J_ptᵀ r_p over each pixel's three residuals, D_t its block of JᵀJ
    g = np.einsum("pcj,pc->pj", jac.reshape(-1, 3, 64 * k), r.reshape(-1, 3)).reshape(-1, 64, k)
    meat = np.einsum("pti,ptj->tij", g, g) * r.size / (r.size - 64 * k)
    d_inv = np.linalg.inv(np.stack([h[u * k:(u + 1) * k, u * k:(u + 1) * k] for u in range(64)]))
    ratio = np.einsum("tci,tij,tcj->tc", d_inv, meat, d_inv) / (sigma2 * np.diagonal(d_inv, axis1=1, axis2=2))
    assert np.any(ratio > 1.05) and np.any(ratio < 1)  # under noise alone: around 1, both ways
    np.testing.assert_allclose(got[:, fitted], want * np.sqrt(np.maximum(ratio, 1.0)), rtol=1e-3)


@pytest.mark.parametrize("committed", [False, True])
def test_the_sandwichs_meat_shares_the_jacobians_program(committed):
    """`misfit_ratios` passes the meat's rows to `normal_blocks` placed as the Jacobians are,
    committed to a device or not (a stencil's arrays are; a problem without one need not be), so
    the one program serves both calls."""
    truth = _checker()
    problem = _texel_problem(truth)
    x = jnp.asarray(_stack(truth))
    r, jac, _ = jax.jit(pbrfit.fitting.objective.linearize)(x, problem)
    if committed:
        jac = jax.device_put(jac, jax.devices()[0])
    assert jac.committed == committed
    blocks = pbrfit.fitting.runner._data_blocks.variants[1]  # (the program behind jitted_normal_blocks, small problems)
    blocks.clear_cache()
    seen = np.ones(problem.num_texels, bool)
    ratios = pbrfit.fitting.result.misfit_ratios(problem, np.asarray(x), r, jac, 1e-4, np.ones(5), seen,
                                                 problem.num_pixels)
    assert ratios.shape == (problem.num_texels, 5) and np.all(ratios >= 1.0)
    assert blocks._cache_size() == 1


def test_fixed_channels_stay_fixed():
    """A held map is taken out of the default `fit` (all maps), as ``--roughness`` does."""
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    res = fit_observations(obs, resolution=8, fixed={"roughness": np.asarray(truth.roughness)[..., 0], "metallic": 0},
                           max_steps=20)
    assert res.report["fitted"] == ["base_r", "base_g", "base_b"], res.report["fitted"]
    assert res.report["held"]["roughness"]["source"] == "map" and res.report["held"]["metallic"]["value"] == 0.0
    np.testing.assert_allclose(np.asarray(res.material.roughness), np.asarray(truth.roughness), atol=1e-6)
    assert map_rmse(truth, res)["base_color"] < 0.01


def test_fit_arguments_resolve_and_refuse():
    assert fit_arguments() == (("base_color", "metallic", "roughness"), {})
    fit, fixed = fit_arguments(None, {"roughness": 0.3, "base_color": [0.2, 0.3, 0.4]})
    assert fit == ("metallic",) and fixed["roughness"].shape == () and fixed["base_color"].shape == (3,)
    assert fit_arguments("base_color, normal")[0] == ("base_color", "normal")
    assert fit_arguments(None, {"metallic": np.zeros((4, 4))})[1]["metallic"].shape == (4, 4, 1)
    for fit, fixed, match in ((("roughness",), {"roughness": 0.3}, "fixed holds too"),
                              (None, {"base_color": 0.5, "metallic": 0.0, "roughness": 0.5}, "nothing to fit"),
                              (("albedo",), None, "unknown map 'albedo'"), (("metallic", "metallic"), None, "twice"),
                              (None, {"normal": 0.5}, "can only be fitted"), (None, {"roughness": 2.0}, r"\[0, 1\]"),
                              (None, {"roughness": float("nan")}, "NaN"),
                              (None, {"base_color": np.ones((4, 4, 4))}, r"\(H, W, 3\)"),
                              (None, {"roughness": "rough"}, "expected numbers"),
                              (None, {"roughness": "0.5"}, "expected numbers")):
        with pytest.raises(ValueError, match=match):
            fit_arguments(fit, fixed)


@pytest.mark.parametrize("options, match", [
    (dict(resolution=0), "resolution"), (dict(resolution=8.5), "resolution"), (dict(resolution=(8, 8, 8)), "resolution"),
    (dict(resolution=[8]), "resolution"),
    (dict(max_steps=0), "max_steps"), (dict(smooth=-1.0), "smooth"), (dict(smooth=float("nan")), "smooth"),
    (dict(loss="huber", loss_scale=0.0), "loss_scale"), (dict(rtol=float("inf")), "rtol"),
    (dict(solver="lm", cg_rtol=0.1), "cg_rtol"), (dict(solver="lm", continuation=(0.1, 0.01)), "continuation"),
    (dict(maps="none", resolution=8), "maps='none'"), (dict(maps="none", smooth=0.1), "maps='none'"),
    (dict(maps="none", coarse_to_fine=True), "maps='none'"),
    (dict(cg_rtol=0.0), "cg_rtol"), (dict(cg_rtol=float("nan")), "cg_rtol"), (dict(coarse_steps=-1), "coarse_steps"),
    (dict(uncertainty_radius=3), "uncertainty_radius"), (dict(max_steps=True), "max_steps"),
    (dict(search="no"), "search: expected True or False"), (dict(repair=1), "repair: expected True or False"),
    (dict(progress=5), "progress: expected a function"), (dict(level_factor=0), "level_factor: expected an integer >= 2"),
    (dict(devices="cpu"), "devices: expected a sequence of JAX devices"), (dict(devices=[]), "devices"),
    (dict(model=Model(metallic=False)), "metallic is fitted, and the model has no metal lobe"),
    (dict(model="ggx"), "model: expected a pbrfit.Model"), (dict(devices=jax.devices()[0]), "devices"),
    (dict(noise_level="bad"), "noise_level"), (dict(loss="l3"), "loss"), (dict(init="foo"), "init"),
    (dict(wrap="x"), "wrap"), (dict(solver="newton"), "solver: must be one of structured, lm"),
    (dict(maps="uv"), "maps: must be 'texture' or 'none', got 'uv'"),
    (dict(smooth=True), "smooth: must be a finite number >= 0, got True"), (dict(rtol=1j), "rtol: must be a finite"),
    (dict(loss="huber", loss_scale=np.complex64(1)), "loss_scale"), (dict(continuation=(True,)), "continuation"),
])
def test_fit_refuses_options_out_of_range_or_unread(options, match):
    """Refused before any work (no compile: these run in milliseconds); the command line refuses
    the same (`tests/test_cli_fit.py`)."""
    obs = observations_from_views(VIEWS[:1], [np.zeros((RES, RES, 3), np.float32)])
    with pytest.raises(ValueError, match=match):
        fit_observations(obs, **options)
    # pbrfit.fit checks them before it reads the capture: a path to nothing is not reached
    with pytest.raises(ValueError, match=match) as caught:
        pbrfit.fit("/nonexistent/capture", **options)
    assert "nonexistent" not in str(caught.value)


def test_srgb_targets_and_huber_loss():
    """sRGB targets with 3% of the pixels knocked dark (0.05): the Huber fit keeps to the truth,
    the L2 fit is pulled off it (measured: base 0.003 / 0.031 off, roughness 0.0009 / 0.014)."""
    truth = Material.uniform((0.5, 0.4, 0.3), 0.0, 0.4)
    rng = np.random.default_rng(1)
    images = []
    for image in _images(VIEWS, truth, color_space="srgb"):
        image = image.copy()
        image[rng.random(image.shape[:2]) < 0.03] = 0.05
        images.append(image)
    obs = observations_from_views(VIEWS, images, color_space="srgb")
    fits = {loss: fit_observations(obs, maps="none", loss=loss, max_steps=40) for loss in ("huber", "l2")}
    error = {loss: (np.max(np.abs(np.asarray(r.material.base_color).ravel() - [0.5, 0.4, 0.3])),
                    abs(float(r.material.roughness[0, 0, 0]) - 0.4)) for loss, r in fits.items()}
    assert fits["huber"].report["loss"] == "huber" and fits["l2"].report["loss"] == "l2"
    assert fits["huber"].report["loss_scale"] == pytest.approx(LOSS_SCALE) and "loss_scale" not in fits["l2"].report
    assert error["huber"][0] < 0.008 and error["huber"][1] < 3e-3, error
    assert error["l2"][0] > 0.015 and error["l2"][1] > 6e-3, error
    assert fits["huber"].report["uniform_check"] == dict(skipped="a uniform material")


@pytest.mark.parametrize("solver", [s for s in SOLVERS if s != "structured"])
def test_every_solver_runs(solver):
    truth = Material.uniform((0.6, 0.35, 0.2), 0.0, 0.35)
    obs = observations_from_views(VIEWS[:2], _images(VIEWS[:2], truth))
    seen = []
    res = fit_observations(obs, resolution=4, solver=solver, max_steps=3, init="prior", progress=seen.append)
    assert res.report["solver"] == solver
    assert 1 <= res.report["steps"] <= 3, res.report["levels"]  # it ran, and max_steps reached it
    assert np.isfinite(res.report["final_loss"])
    # progress (the CLI's bar and convergence.png): the objective at each evaluation, one per
    # step, the first at the prior (metallic 0 moved `START_MARGIN` inside: 17.9297 on the
    # bound), the same for every solver
    losses = [entry["loss"] for entry in seen if "loss" in entry]
    assert len(losses) == res.report["steps"] and np.all(np.isfinite(losses)), seen
    assert not any("budget" in entry for entry in seen)  # they count evaluations, not a solve's steps
    assert losses[0] == pytest.approx(17.8896, rel=1e-4)
    # from the prior's 0.5, the three steps of every solver with a damping or a line search move
    # base colour towards the truth (measured: RMSE 0.011 (lm) to 0.175 (adam), against the
    # prior's 0.202); gn's undamped first steps overshoot (metallic to 0.99, RMSE 0.24), and so do
    # dogleg's trial steps, which its trust region refuses: in float64 its three steps stay at the
    # prior, and in float32 the rounding of the Jacobian's transpose decides whether the third is
    # taken (images scaled by 1 ± 1e-6 sent its first trial to E = 34, 75 or 46). Their ten steps
    # are checked in `test_optx_solvers_move_a_channel_started_on_its_bound`.
    rmse = float(np.sqrt(np.mean((np.asarray(res.material.base_color) - [0.6, 0.35, 0.2]) ** 2)))
    assert solver in ("gn", "dogleg") or rmse < 0.19, rmse
    if solver == "dogleg":  # a trust region never takes a step that raises E
        assert res.report["final_loss"] <= losses[0] * (1 + 1e-6)


def test_optx_solvers_move_a_channel_started_on_its_bound():
    """The prior holds metallic at 0, where the sine storage's derivative vanishes: the start is
    moved `START_MARGIN` inside (in `optx_solve`, whatever the solver), so the solvers find the
    metal. Measured in 10 steps: gn 0.998 and lm 0.67 (both stayed at exactly 0; gn and dogleg
    stopped after one step); lm is checked. With metallic
    free, a dielectric's normal equations need more than `CG_MAX_STEPS` CG steps in float32,
    which ended gn and dogleg at their first step; their CG is truncated there
    (`truncated_cg`), and in 10 steps dogleg is exact and gn halves its base colour error."""
    truth = Material.uniform((0.9, 0.7, 0.3), 1.0, 0.35)
    obs = observations_from_views(VIEWS[:2], _images(VIEWS[:2], truth))
    res = fit_observations(obs, maps="none", solver="lm", max_steps=10, init="prior", search=False,
                           repair=False, uniform_check=False)
    assert float(res.material.metallic[0, 0, 0]) > 0.5, res.material.metallic
    dielectric = Material.uniform((0.6, 0.35, 0.2), 0.0, 0.35)
    obs = observations_from_views(VIEWS[:2], _images(VIEWS[:2], dielectric))
    # measured: base RMSE 0.08 and 4e-5 (the prior 0.202), loss 3.97 and 2e-7 (17.89 at the
    # start), largest metallic 0.14 and 2e-4
    for solver, most, loss in (("gn", 0.1, 5.0), ("dogleg", 1e-3, 1e-5)):
        res = fit_observations(obs, resolution=4, solver=solver, max_steps=10, init="prior", search=False,
                               repair=False, uniform_check=False)
        assert res.report["steps"] == 10, (solver, res.report["levels"])
        rmse = float(np.sqrt(np.mean((np.asarray(res.material.base_color) - [0.6, 0.35, 0.2]) ** 2)))
        assert rmse < most and res.report["final_loss"] < loss, (solver, rmse, res.report["final_loss"])
        assert float(np.max(np.asarray(res.material.metallic))) < 0.2, solver


def _texel_problem(truth, smooth=0.0, on_grid=False):
    """The fit's problem of `truth`'s images; `on_grid`: with its map's grid and stencil, as a fit
    makes it (`pbrfit.fitting.stencil`), else the products go through the pixels."""
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    shape = truth.resolution
    layout = texel_layout(obs, shape)
    t = shape[0] * shape[1]
    pairs = neighbour_pairs(shape)
    free = np.ones((t, 5), np.float32)
    problem = Problem(obs, layout.index, layout.weight, jnp.asarray(free), jnp.asarray(pairs),
                      jnp.ones(len(pairs), jnp.float32), jnp.asarray(smooth, jnp.float32), jnp.asarray(0.05, jnp.float32),
                      None, Model(), "l2", texel_grid(shape, t) if on_grid else None)
    return with_stencil(problem)


def _stack(material):
    return jnp.concatenate([material.base_color, material.metallic, material.roughness], -1).reshape(-1, 5)


@jax.jit
def _dense_jacobian(x, problem):
    """∂r/∂x, dense: the pixel residuals (flattened) against the (T, 5) maps (flattened),
    forward mode (jitted: eager, a 64-texel map's 320 columns took 6 s)."""
    return jax.jacfwd(lambda v: pbrfit.fitting.objective.pixel_residuals(v.reshape(-1, 5), problem).ravel())(x.ravel())


@pytest.mark.parametrize("on_grid", [False, True])
def test_grid_start_solves_base_colour_jointly_at_colour_edges(on_grid):
    """Every pixel of the checker mixes texels of both colours. The grid start solves all base
    colours jointly, so each comes out right (solved texel by texel, as if a pixel showed only the
    texel being solved, they were up to 0.15 off) and each roughness stays in its basin; the same
    by stencil and through the pixels."""
    truth = _checker()
    x_true = np.asarray(_stack(truth))
    problem = _texel_problem(truth, on_grid=on_grid)
    assert (problem.stencil is not None) == on_grid
    x = np.asarray(grid_initialise(jnp.asarray(x_true), problem))
    assert np.abs(x[:, :3] - x_true[:, :3]).max() < 0.02, np.abs(x[:, :3] - x_true[:, :3]).max()
    assert np.abs(x[:, 4] - x_true[:, 4]).max() < 0.09 and np.all(x[:, 3] == 0.0)


@pytest.mark.parametrize("on_grid", [False, True])
def test_joint_base_colour_solve_matches_a_dense_solve(monkeypatch, on_grid):
    """`_solve_base_joint` is least squares over all texels at once: it converges to the base
    colours that made the pixels (a dense solve's answer), 3 steps already close; rows with zero
    slope and all-zero channels stay finite. By stencil (`on_grid`) each step is the step through
    the pixels, to float32 rounding."""
    from pbrfit.fitting.initialisation import _solve_base, _solve_base_joint

    truth = _checker()
    problem = _texel_problem(truth, on_grid=on_grid)
    rng = np.random.default_rng(0)
    p, t = problem.index.shape[0], problem.num_texels
    b_true = jnp.asarray(rng.uniform(0.2, 0.8, (t, 3)), jnp.float32)
    a = rng.uniform(0.2, 1.0, (p, 3)).astype(np.float32)
    a[::7] = 0.0  # pixels whose radiance does not depend on the base colour
    a[:, 2] = 0.0  # a channel no pixel constrains
    a, l0 = jnp.asarray(a), jnp.asarray(rng.uniform(0.0, 0.1, (p, 3)), jnp.float32)
    y = l0 + a * pbrfit.fitting.objective.sample_texels(b_true, problem)
    err = {n: np.abs(np.asarray(_solve_base_joint(l0, a, y, problem, n)) - np.asarray(b_true))[:, :2].max()
           for n in (0, 3, 40)}
    per_texel = np.abs(np.asarray(_solve_base(l0, a, y, problem.weight, problem)) - np.asarray(b_true))[:, :2].max()
    assert err[40] < 1e-4 and err[3] < 0.25 * per_texel and err[0] == pytest.approx(per_texel, abs=1e-6), (err, per_texel)
    out = np.asarray(_solve_base_joint(l0, a, y, problem, 3))
    assert np.all(np.isfinite(out)) and np.all(out[:, 2] == 0.0)
    if on_grid:
        through_pixels = dataclasses.replace(problem, stencil=None)
        for n in (0, 1, 3):
            np.testing.assert_allclose(np.asarray(_solve_base_joint(l0, a, y, problem, n)),
                                       np.asarray(_solve_base_joint(l0, a, y, through_pixels, n)), rtol=0, atol=2e-6)
    # the knob: the module's GRID_BASE_CG_STEPS is the default step count (equal to float32
    # rounding, not to the bit: a GPU's scatter-adds sum in no fixed order, so two runs of one
    # program can differ in the last digits; 3 steps against 40 differ by far more)
    monkeypatch.setattr(pbrfit.fitting.initialisation, "GRID_BASE_CG_STEPS", 40)
    by_default = np.asarray(_solve_base_joint(l0, a, y, problem))
    np.testing.assert_allclose(by_default, np.asarray(_solve_base_joint(l0, a, y, problem, 40)), rtol=0, atol=1e-5)
    assert np.abs(by_default - out).max() > 1e-3


def test_grid_start_assembles_one_normal_matrix_for_the_candidates_at_metallic_0(monkeypatch):
    """Under punctual lights with Lambert's diffuse lobe, a pixel's slope in base colour at
    metallic 0 is the same at every roughness, and Burley's is not; so the grid start's
    candidates at metallic 0 share one AᵀA, and start where each candidate assembling its own
    starts: with metallic free (half the texels metal; texels start at metallic 1), and held at
    0.5 (no candidate at metallic 0 then)."""
    from pbrfit.fitting.initialisation import _slope_blocks_shared
    from pbrfit.render.shade import shade

    checker = _checker()
    truth = Material(checker.base_color, (checker.roughness > 0.4).astype(jnp.float32), checker.roughness)  # half metal
    problem = _texel_problem(truth, on_grid=True)
    obs, p = problem.obs, problem.num_pixels
    zero = jnp.zeros((p, 3))

    def slope(model, roughness):
        render = lambda b: shade(obs.normal, obs.view, obs.light_l, obs.light_radiance, b,  # noqa: E731
                                 jnp.zeros((p, 1)), jnp.full((p, 1), roughness), model)
        return np.asarray(jax.jvp(render, (zero,), (jnp.ones_like(zero),))[1])

    assert np.any(slope(Model(), 0.2) > 0)
    np.testing.assert_array_equal(slope(Model(), 0.2), slope(Model(), 0.9))
    assert np.abs(slope(Model(diffuse="burley"), 0.2) - slope(Model(diffuse="burley"), 0.9)).max() > 1e-3
    assert _slope_blocks_shared(problem)
    assert not _slope_blocks_shared(dataclasses.replace(problem, model=Model(diffuse="burley")))
    assert not _slope_blocks_shared(dataclasses.replace(problem, stencil=None))

    x_true = np.asarray(_stack(truth))
    held = x_true.copy()
    held[:, 3] = 0.5
    # traced afresh each time (a new function), so that the second trace reads the patch
    start = jax.jit(lambda x, pr: pbrfit.fitting.initialisation.grid_initialise.__wrapped__(x, pr))
    cases = [(x_true, problem), (held, dataclasses.replace(problem, free=problem.free.at[:, 3].set(0.0)))]
    shared = [np.asarray(start(jnp.asarray(x), pr)) for x, pr in cases]
    monkeypatch.setattr(pbrfit.fitting.initialisation, "_slope_blocks_shared", lambda problem: False)
    start = jax.jit(lambda x, pr: pbrfit.fitting.initialisation.grid_initialise.__wrapped__(x, pr))
    for (x, pr), one in zip(cases, shared):
        np.testing.assert_allclose(one, np.asarray(start(jnp.asarray(x), pr)), rtol=0, atol=1e-6)
    assert np.any(shared[0][:, 3] == 1.0) and np.all(shared[1][:, 3] == 0.5)


@pytest.mark.parametrize("tonemap,ev,bits", [("reinhard", 1.0, None), ("aces_hill", 1.0, None),
                                             ("khronos_neutral", 1.0, None), ("aces_narkowicz", 3.0, 8),
                                             ("reinhard", 3.0, 8)])
def test_grid_start_inverts_the_tone_map(tonemap, ev, bits):
    """On tone-mapped sRGB images the grid start solves base colour in linear radiance from the
    inverted tone map, as well as on linear images; also from 8-bit images exposed so bright
    that their highlights sit in the top codes, where one code spans a large range of radiance
    (the fit weights those pixels by the tone map's slope)."""
    truth = _checker()
    imgs = []
    for vi in VIEWS:
        img = np.zeros((vi.shape[0] * vi.shape[1], 3), np.float32)
        img[np.asarray(vi.pixel)] = np.asarray(encode(radiance_view(vi, truth, Model()), ev, tonemap, "srgb"))
        if bits:
            img = np.minimum(np.round(img * (2**bits - 1)), 2**bits - 2) / (2**bits - 1)  # no saturated code
        imgs.append(img.reshape(vi.shape + (3,)))
    obs = observations_from_views(VIEWS, imgs, exposures=[ev] * len(VIEWS), tonemap=tonemap, color_space="srgb")
    problem = dataclasses.replace(_texel_problem(truth), obs=obs)
    x_true = np.asarray(_stack(truth))
    x = np.asarray(grid_initialise(jnp.asarray(x_true), problem))
    assert np.abs(x[:, :3] - x_true[:, :3]).max() < 0.02, np.abs(x[:, :3] - x_true[:, :3]).max()
    assert np.abs(x[:, 4] - x_true[:, 4]).max() < 0.11 and np.all(x[:, 3] == 0.0)  # 0.08 on linear images
    if bits:  # without the slope weights: 0.104 (and base colour 0.015-0.017)
        assert np.abs(x[:, 4] - x_true[:, 4]).max() < 0.095


@pytest.mark.parametrize("smooth", [0.0, 1e-3])
def test_coordinate_search_repairs_texels_in_wrong_basins(smooth):
    """Texels knocked into a wrong (metallic, roughness) basin come back, and the objective falls
    tenfold. Their neighbours, which share pixels with them, move too (38 of 59 by up to 0.28 while
    the knocked texels are wrong); a solve from the search's result reaches the optimum."""
    truth = _checker()
    problem = _texel_problem(truth, smooth)
    x_true = _stack(truth)
    wrong = np.asarray(x_true).copy()
    knocked = np.array([9, 18, 27, 45, 54])  # every parity class
    wrong[knocked, 3] = 1.0
    wrong[knocked, 4] = 0.9
    x = coordinate_search(jnp.asarray(wrong), problem, jnp.asarray(parity_classes(truth.resolution)))
    energy = jax.jit(objective)
    assert float(energy(x, problem)) < 0.1 * float(energy(jnp.asarray(wrong), problem))
    got = np.asarray(x)
    assert np.all(got[knocked, 3] == 0.0)
    # the roughness grid is geometric (ratio SEARCH_ROUGHNESS_RATIO): within one step of the truth
    ratio = got[knocked, 4] / np.asarray(x_true)[knocked, 4]
    assert np.all((ratio < SEARCH_ROUGHNESS_RATIO) & (ratio > 1 / SEARCH_ROUGHNESS_RATIO)), got[knocked]
    # the neighbours bent towards the knocked texels while those were wrong; a solve finishes (to
    # the end: with the prior on, the noise-relative stop would leave a roughness that changes E by
    # 2e-9 some 0.02 away, far within its standard error but not within this test's 2e-3)
    full = StructuredLM(noise_rtol=0.0)
    polished = np.asarray(solve(x, problem, full, max_steps=jnp.asarray(40))[0])
    optimum = np.asarray(solve(x_true, problem, full, max_steps=jnp.asarray(40))[0])  # the truth, unless smooth > 0
    np.testing.assert_allclose(polished, optimum, atol=2e-3)


@pytest.mark.parametrize("ibl", [None, "per_pixel", "split_sum"])
def test_the_split_sums_candidates_are_shaded_once_and_unchanged(ibl):
    """The grid start's and the search's shaded rows pass through a conditional under the split
    sum alone (`_shaded_once`: XLA then stores them instead of shading them again in each fusion
    that reads them), and come back unchanged, a NaN in the first row included."""
    from types import SimpleNamespace
    from pbrfit.fitting.initialisation import _shaded_once

    problem = SimpleNamespace(model=Model(ibl=ibl))
    radiance = jnp.asarray([[jnp.nan, 0.5, 2.0], [jnp.inf, 0.0, 1e-30]], jnp.float32)
    slope = jnp.asarray([[0.25, -1.0, 3.0], [0.0, 7.0, 1e30]], jnp.float32)
    out = jax.jit(lambda a, b: _shaded_once(problem, a, b))(radiance, slope)
    for got, want in zip(out, (radiance, slope)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    primitives = {e.primitive.name for e in jax.make_jaxpr(lambda a, b: _shaded_once(problem, a, b))(radiance, slope).eqns}
    assert ("cond" in primitives) == (ibl == "split_sum"), primitives
    empty = jnp.zeros((0, 3), jnp.float32)  # no rows: nothing to store
    assert [a.shape for a in _shaded_once(problem, empty, empty)] == [(0, 3), (0, 3)]


def test_the_best_candidate_is_the_first_least_score_as_argmin_reads_it():
    """The grid start and the search keep each texel's best candidate as they score them: the
    first of the least scores, a NaN counting as least (`jnp.argmin`), with its base colour."""
    nan = np.nan
    scores = jnp.asarray([[3.0, 1.0, nan, 2.0, 4.0], [1.0, 1.0, nan, 5.0, nan], [0.0, 2.0, nan, nan, 1.0]])
    bases = jnp.asarray(np.random.default_rng(0).random((3, 5, 3)), jnp.float32)
    index, base = pbrfit.fitting.initialisation._best_candidates(lambda k: (bases[k], scores[k]), jnp.arange(3))
    want = jnp.argmin(scores, axis=0)
    np.testing.assert_array_equal(index, want)
    np.testing.assert_array_equal(index, [2, 0, 0, 2, 1])
    np.testing.assert_array_equal(base, bases[want, jnp.arange(5)])


def test_coordinate_search_tries_blended_metallic():
    """Texels of a half-metal square stuck at the metallic bound move to the blend candidate."""
    checker = _checker()
    c = np.asarray(checker.roughness) > 0.4  # the squares with roughness 0.45
    truth = Material(checker.base_color, jnp.asarray(np.where(c, 0.5, 0.0), jnp.float32), checker.roughness)
    problem = _texel_problem(truth, 0.0)
    x_true = np.asarray(_stack(truth))
    knocked = np.flatnonzero(x_true[:, 3] == 0.5)[::3]
    wrong = x_true.copy()
    wrong[knocked, 3] = 0.0
    wrong[knocked, 4] *= 1.15
    classes = jnp.asarray(parity_classes(truth.resolution))
    x = np.asarray(coordinate_search(jnp.asarray(wrong), problem, classes))
    assert np.all((x[knocked, 3] > 0.0) & (x[knocked, 3] < 1.0)), x[knocked]  # a blend candidate
    # without the blends the class texels can only try metallic 0 or 1
    plain = np.asarray(coordinate_search(jnp.asarray(wrong), problem, classes, 1, False))
    assert set(np.unique(plain[knocked, 3])) <= {0.0, 1.0}
    energy = jax.jit(objective)
    assert float(energy(jnp.asarray(x), problem)) < float(energy(jnp.asarray(plain), problem))
    # from the blend a solve reaches the truth
    polished = np.asarray(solve(jnp.asarray(x), problem, max_steps=jnp.asarray(40))[0])
    np.testing.assert_allclose(polished, x_true, atol=2e-3)


def test_coordinate_search_never_raises_the_objective():
    truth = _checker()
    problem = _texel_problem(truth, 1e-3)
    rng = np.random.default_rng(3)
    x0 = jnp.asarray(rng.uniform(LOWER, UPPER, (64, 5)).astype(np.float32))
    x = coordinate_search(x0, problem, jnp.asarray(parity_classes(truth.resolution)))
    energy = jax.jit(objective)
    assert float(energy(x, problem)) <= float(energy(x0, problem))
    assert float(energy(x, problem)) < 0.5 * float(energy(x0, problem))


def test_coordinate_search_checks_the_whole_objective_only_where_classes_share_pixels():
    """On an even-sized map no pixel reads two texels of a parity class, and the search without
    the whole objective's check moves the texels as the one with it; on an odd-sized wrapped map
    the seam's cells hold two texels of a class, and the check is needed."""
    truth = _checker()
    problem = _texel_problem(truth, 1e-3)
    classes = parity_classes(truth.resolution)
    assert classes_share_no_pixel(problem, classes)
    odd = texel_layout(problem.obs, (7, 7))
    assert not classes_share_no_pixel(dataclasses.replace(problem, index=odd.index, weight=odd.weight),
                                      parity_classes((7, 7)))
    x0 = jnp.asarray(np.random.default_rng(5).uniform(LOWER, UPPER, (64, 5)).astype(np.float32))
    checked = np.asarray(coordinate_search(x0, problem, jnp.asarray(classes)))
    unchecked = np.asarray(coordinate_search(x0, problem, jnp.asarray(classes), 1, True, True))
    assert np.any(checked != np.asarray(x0))
    np.testing.assert_allclose(unchecked, checked, atol=1e-6)


def _two_samples(problem, truth):
    """``problem`` with each pixel's row twice, its uv moved either way: two samples per pixel."""
    rows = {name: np.repeat(np.asarray(getattr(problem.obs, name)), 2, axis=0) for name in PIXEL_FIELDS}
    rows["uv"] = rows["uv"] + np.tile([[-0.004, 0.003], [0.004, -0.003]], (problem.obs.num_rows, 1)).astype(np.float32)
    obs = dataclasses.replace(problem.obs, samples=2, **{k: jnp.asarray(v) for k, v in rows.items()})
    layout = texel_layout(obs, truth.resolution)
    return with_stencil(dataclasses.replace(problem, obs=obs, index=layout.index, weight=layout.weight))


@pytest.mark.parametrize("on_grid,samples", [(False, 1), (True, 2)])
def test_coordinate_search_over_the_pixels_of_the_moving_texels_alone(on_grid, samples):
    """The repair's search: where only some texels are free, a search over the pixels that read
    them (`moving_pixels`, `take_pixels`) moves them as the search over every pixel does, and so
    does one over the texels those pixels read alone (`take_texels`, the prior's pairs of the
    moving texels kept); also with the map's grid (as a fit's problem has it) and two samples per
    pixel."""
    truth = _checker()
    problem = _texel_problem(truth, 1e-3, on_grid)
    if samples > 1:
        problem = _two_samples(problem, truth)
    moving = np.zeros(problem.num_texels, bool)
    moving[[9, 10, 17, 18, 45, 46]] = True
    region = dataclasses.replace(problem, free=problem.free * jnp.asarray(moving[:, None], jnp.float32))
    pixels = moving_pixels(moving, np.asarray(problem.index), np.asarray(problem.weight), problem.samples)
    assert 0 < len(pixels) < problem.num_pixels // 3
    sub = take_pixels(region, pixels, len(pixels) + 3)
    classes = jnp.asarray(parity_classes(truth.resolution))
    x0 = np.asarray(_stack(truth)).copy()
    x0[moving, 3:5] = [1.0, 0.9]
    whole = np.asarray(coordinate_search(jnp.asarray(x0), region, classes))
    alone = np.asarray(coordinate_search(jnp.asarray(x0), sub, classes))
    assert np.all(alone[~moving] == x0[~moving]) and np.all(alone[moving, 3] == 0.0)
    np.testing.assert_allclose(alone, whole, atol=1e-5)
    part, texels = take_texels(sub)
    real = texels < problem.num_texels
    # two samples a pixel read more cells: 52 texels, padded to the whole map's 64
    assert part.num_texels == (32 if samples == 1 else 64) and np.sum(real) == (28 if samples == 1 else 52)
    assert set(np.flatnonzero(moving)) <= set(texels[real])
    both = np.all(np.isin(np.asarray(problem.pairs), texels[real]), axis=1)
    assert (part.grid is None) == (not on_grid) and np.sum(np.asarray(part.pair_weight) > 0) == np.sum(both)
    padded = lambda a: np.concatenate([a, a[:1]])[texels]
    found = np.asarray(coordinate_search(jnp.asarray(padded(x0)), part, jnp.asarray(padded(np.asarray(classes)))))
    assert np.all(found[~real] == padded(x0)[~real])
    np.testing.assert_allclose(found[real], whole[texels[real]], atol=1e-5)
    # a larger count whose program is compiled is taken instead (`texel_program`), with its shapes
    shapes = lambda p: (p.free.shape[0], p.pairs.shape[0])
    wider = (64, problem.pairs.shape[0])
    assert texel_program(region, part, shapes, lambda k: k == wider) == (64, wider)
    assert texel_program(region, part, shapes, lambda k: False) == (part.num_texels, shapes(part))
    if samples == 1:
        wide, wide_texels = take_texels(sub, size=64)
        assert wide.free.shape == (64, 5) and wide.pairs.shape == problem.pairs.shape
        np.testing.assert_array_equal(wide_texels[:28], texels[:28])
        with pytest.raises(ValueError):
            take_texels(sub, size=16)
    # over the pixels of one cell, which leave the moving texels' partners across it and texels
    # 45, 46 unread: the moving texels' local energies (their pixels' and prior pairs') are the same
    cell = pixels[np.asarray(problem.index).reshape(problem.num_pixels, -1)[pixels, 0] == 9]
    few = take_pixels(region, cell, len(cell))
    part, texels = take_texels(few)
    x = np.random.default_rng(0).uniform(0.1, 0.9, x0.shape).astype(np.float32)
    local = np.asarray(pbrfit.fitting.initialisation._energies(jnp.asarray(padded(x)), part)[0])
    at = np.flatnonzero(np.isin(texels, np.flatnonzero(moving)))
    np.testing.assert_allclose(local[at], np.asarray(pbrfit.fitting.initialisation._energies(
        jnp.asarray(x), few)[0])[texels[at]], rtol=1e-6)


def test_repair_searches_the_moving_texels_pixels_alone_where_that_costs_less(monkeypatch):
    """`search_problem`: a search's time in proportion to its pixels, plus `SEARCH_COMPILE_COST`
    (at most `SEARCH_COMPILE_PIXELS`) where its size's program is not compiled."""
    problem = _texel_problem(_checker(), 1e-3)
    key = ("coordinate_search", (8, 8), True) + pbrfit.fitting.runner.problem_key(problem)
    size_key = lambda n: key[:4] + ((n, 4),) + key[5:]

    class Compiled:
        def __init__(self, *keys):
            self.keys = keys

        def has(self, k):
            return k in self.keys

    assert SEARCH_COMPILE_COST + 1 / 8 < 1 <= SEARCH_COMPILE_COST + 1 / 4  # a tie keeps the whole problem
    few, quarter = np.arange(150), np.arange(300)  # of 1444 pixels: 1/8 is 181, 1/4 is 361
    # the whole problem's program is compiled: another pays for its compile at 1/8, not at 1/4
    sub, sub_key, texels = search_problem(problem, few, key, Compiled(key))
    # every texel is free, so the prior keeps each one's pairs: all are taken
    assert sub.num_pixels == 181 and sub_key == size_key(181) and np.array_equal(texels, np.arange(64))
    assert search_problem(problem, quarter, key, Compiled(key)) == (problem, key, None)
    # a size already compiled needs no compile: the one for 1/4 rather than compiling 1/8's
    assert search_problem(problem, few, key, Compiled(key, size_key(361)))[1] == size_key(361)
    # nothing compiled yet (the repair's problem is not the fit's search's): the smallest size
    assert search_problem(problem, quarter, key, Compiled())[1] == size_key(361)
    # where a compile costs less than a search of 1/4 of the pixels (a large map's), 1/4 pays
    monkeypatch.setattr(pbrfit.fitting.stages.repair, "SEARCH_COMPILE_PIXELS", 200)
    assert search_problem(problem, quarter, key, Compiled(key))[1] == size_key(361)


def test_a_refit_runs_over_the_moving_texels_pixels_where_that_costs_less(monkeypatch):
    """`Runner.refit`: steps over the pixels that read the texels that move (the others' term
    kept, `LeftOut`; conjugate gradients over those texels alone, `Problem.texels`) reach the
    texel values, steps and E that steps over every pixel reach, and leave the whole problem's
    linearisation (its start's, those pixels' rows replaced); it takes that way where a compile
    counts for nothing, and on a problem this small (its steps cost less than the compile) every
    pixel."""
    truth = _checker()
    problem = _texel_problem(truth, 1e-3, on_grid=True)
    moving = np.zeros(problem.num_texels, bool)
    moving[[0, 9, 10, 17, 18, 63]] = True  # a 2 × 2 patch, the first texel and the last
    region = dataclasses.replace(problem, free=problem.free * jnp.asarray(moving[:, None], jnp.float32))
    x0 = np.asarray(_stack(truth)).copy()
    x0[moving] = [0.5, 0.5, 0.5, 0.2, 0.6]
    start = jax.jit(pbrfit.fitting.objective.linearize)(jnp.asarray(x0), problem)[:2]
    num_free = int(np.sum(np.asarray(region.free)))

    def run(refit):
        runner = pbrfit.fitting.runner.Runner(StructuredLM(), None, pbrfit.fitting.runner.Compiler(
            dict(compile=0.0, solve=0.0), background=False))
        x, info = (runner.refit(jnp.asarray(x0), region, moving, 10, num_free, start) if refit
                   else runner(jnp.asarray(x0), region, 10, num_free))
        # (its texels, whether it leaves pixels out, its CG's texels)
        programs = [(key[3][0],) + key[-2:] for key in runner.compiler.done]
        return np.asarray(x), info, runner.linearization, programs

    whole = run(False)
    assert run(True)[3] == [(64, False, None)]  # the steps of 1444 pixels cost less than a compile
    monkeypatch.setattr(pbrfit.fitting.runner, "REFIT_COMPILE_ROW_STEPS", 0)
    x, info, (r, jac), programs = run(True)
    # the steps over some pixels and the 32 texels they read, conjugate gradients over the 6 free
    # texels (8 rows), no other program
    assert programs == [(32, True, 8)]
    assert info == whole[1] and info["steps"] > 2
    np.testing.assert_allclose(x, whole[0], atol=1e-5)
    assert np.all(x[~moving] == x0[~moving])
    assert r.shape == whole[2][0].shape and jac.shape == whole[2][1].shape
    np.testing.assert_allclose(np.asarray(r), np.asarray(whole[2][0]), atol=1e-5)
    np.testing.assert_allclose(np.asarray(jac), np.asarray(whole[2][1]), atol=1e-4)
    # its problem's objective is the whole problem's wherever the moving texels go: the pixels left
    # out and the prior's pairs dropped (both ends held) kept as a term
    pixels = moving_pixels(moving, np.asarray(problem.index), np.asarray(problem.weight), 1)
    sub, texels = take_texels(take_pixels(region, pixels, len(pixels), start[0]), x0)
    live_pairs = lambda p: np.sum(np.asarray(p.pair_weight) > 0)
    assert sub.stencil is not None and live_pairs(sub) < live_pairs(problem)
    moved = x0.copy()
    moved[moving] = np.random.default_rng(1).uniform(0.1, 0.9, (int(np.sum(moving)), 5))
    far = np.random.default_rng(2).uniform(0.1, 0.9, x0.shape).astype(np.float32)  # the prior's terms large
    for x_start, x in ((x0, moved), (far, np.where(moving[:, None], moved, far))):
        sub, texels = take_texels(take_pixels(region, pixels, len(pixels), jax.jit(pbrfit.fitting.objective.linearize)(
            jnp.asarray(x_start), problem)[0]), x_start)
        np.testing.assert_allclose(float(objective(jnp.asarray(texel_rows(x, texels)), sub)),
                                   float(objective(jnp.asarray(x, jnp.float32), region)), rtol=1e-5)


def test_a_refits_cost_counts_sample_rows(monkeypatch):
    """`Runner.refit` weighs a program's compile against its steps' sample rows, not pixels: with
    two samples a pixel, a compile worth 1.5 steps' of the pixels it leaves out is paid for (in
    pixels it would not be)."""
    truth = _checker()
    problem = _two_samples(_texel_problem(truth, 1e-3, on_grid=True), truth)
    moving = np.zeros(problem.num_texels, bool)
    moving[[9, 10, 17, 18]] = True
    region = dataclasses.replace(problem, free=problem.free * jnp.asarray(moving[:, None], jnp.float32))
    pixels = moving_pixels(moving, np.asarray(problem.index), np.asarray(problem.weight), problem.samples)
    smallest = halving_sizes(problem.num_pixels, len(pixels), 1)[-1]
    assert smallest < problem.num_pixels
    steps, taken = 10, []

    class Probe(pbrfit.fitting.runner.Runner):
        def __call__(self, x0, problem, steps, num_free):  # which problem it runs, no run
            taken.append(problem.num_pixels)
            raise StopIteration

    runner = Probe(StructuredLM(), None, pbrfit.fitting.runner.Compiler(dict(compile=0.0, solve=0.0), False))
    start = (jnp.zeros((problem.num_pixels, 3)), None)
    left_out = problem.num_pixels - smallest
    for worth in (1.5, 2.5):
        monkeypatch.setattr(pbrfit.fitting.runner, "REFIT_COMPILE_ROW_STEPS", worth * steps * left_out)
        with pytest.raises(StopIteration):
            runner.refit(jnp.asarray(_stack(truth)), region, moving, steps, 1, start)
    assert taken == [smallest, problem.num_pixels]


def test_put_back_clusters_take_their_pixels_rows_from_the_start():
    """Where a repair keeps one cluster of moved texels and puts another back, the linearisation
    at the result is the re-fit's for the pixels of the kept one and the start's for the pixels
    of the other (`pbrfit.fitting.runner.pixel_rows_from`): the two share no pixel. Two samples a
    pixel, so that each pixel's rows move with it."""
    truth = _checker()
    problem = _two_samples(_texel_problem(truth, 1e-3, on_grid=True), truth)
    kept, back = [9, 10, 17, 18], [45, 46, 53, 54]
    start = np.asarray(_stack(truth)).copy()
    moved = start.copy()
    moved[kept + back] = [0.3, 0.6, 0.2, 0.0, 0.9]
    result = start.copy()
    result[kept] = moved[kept]
    lin = jax.jit(pbrfit.fitting.objective.linearize)
    at_start, at_moved, want = (lin(jnp.asarray(x), problem)[:2] for x in (start, moved, result))
    index, weight = np.asarray(problem.index), np.asarray(problem.weight)
    pixels = {name: moving_pixels(np.isin(np.arange(problem.num_texels), texels), index, weight, 2)
              for name, texels in (("kept", kept), ("back", back))}
    assert len(pixels["back"]) and not np.intersect1d(pixels["kept"], pixels["back"]).size
    assert np.max(np.abs(np.asarray(at_moved[0])[pixels["back"]] - np.asarray(at_start[0])[pixels["back"]])) > 1e-2
    got = pbrfit.fitting.runner.pixel_rows_from(at_start, pixels["back"], at_moved, 2)
    for a, b in zip(got, want):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)


def test_fit_reports_the_search():
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    res = fit_observations(obs, resolution=8, max_steps=40)
    assert "search_moved" in res.report["levels"][-1] and "search" in res.report["times"]
    # every stage's time, and the rest as "other": they add up to the wall time
    times = res.report["times"]
    assert {"setup", "compile", "solve", "init", "search", "repair", "uniform_check", "post", "other"} <= set(times)
    assert sum(v for k, v in times.items() if k != "compile_background") == pytest.approx(res.report["wall_time"])
    assert res.report["stopping"] == dict(max_steps=40, coarse_steps=COARSE_STEPS, rtol=1e-6, atol=1e-5)
    off = fit_observations(obs, resolution=8, max_steps=40, search=False)
    assert "search_moved" not in off.report["levels"][-1] and "search" not in off.report["times"]


def test_background_compile_gives_the_same_fit():
    """Compiling the solver and the search in a background thread changes when they compile,
    not the fit: equal maps, steps and uncertainty; the report says how much compiled meanwhile."""
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    on = fit_observations(obs, resolution=8, max_steps=40)
    off = fit_observations(obs, resolution=8, max_steps=40, background_compile=False)
    cpu = jax.default_backend() == "cpu"  # a GPU's scatter-adds sum in no fixed order
    for name in ("base_color", "metallic", "roughness"):
        np.testing.assert_allclose(np.asarray(getattr(on.material, name)), np.asarray(getattr(off.material, name)),
                                   rtol=0, atol=0 if cpu else 1e-5)
    # (noiseless: σ is ~1e-7 here, set by the rounding of the residuals)
    np.testing.assert_allclose(on.uncertainty, off.uncertainty, rtol=0 if cpu else 1e-3, atol=0 if cpu else 1e-6)
    if cpu:
        assert on.report["levels"] == off.report["levels"]
    assert "compile_background" in on.report["times"] and "compile_background" not in off.report["times"]


def test_cg_rtol_trades_cg_iterations():
    """A looser CG tolerance takes fewer CG iterations per step and still fits; it is reported,
    and values outside (0, 1) are refused."""
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    tight = fit_observations(obs, resolution=8, max_steps=40)
    loose = fit_observations(obs, resolution=8, max_steps=40, cg_rtol=0.1)
    assert tight.report["cg_rtol"] == pbrfit.fitting.solvers.structured.CG_RTOL and loose.report["cg_rtol"] == 0.1
    per_step = [r.report["levels"][-1]["cg_iterations"] / r.report["levels"][-1]["steps"] for r in (tight, loose)]
    assert per_step[1] < 0.8 * per_step[0], per_step
    err = map_rmse(truth, loose)
    assert err["base_color"] < 0.01 and err["roughness"] < 0.03 and err["metallic"] < 0.02, err
    for bad in (0.0, 1.0):
        with pytest.raises(ValueError, match="cg_rtol"):
            fit_observations(obs, resolution=8, cg_rtol=bad)


def test_coverage_counts_the_fits_own_wrap():
    """coverage.exr counts the taps the fit used: with ``wrap="clamp"`` a pixel near an edge
    reads the edge texels, not those on the far side."""
    truth = _checker()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    res = fit_observations(obs, resolution=8, max_steps=2, wrap="clamp", search=False, continuation=())
    clamp, repeat = (coverage_counts(texel_layout(obs, (8, 8), w)) for w in ("clamp", "repeat"))
    assert np.any(clamp != repeat)
    np.testing.assert_array_equal(res.coverage, clamp)


def test_compiler_prefetches_waits_and_reraises():
    clock = {}
    compiler = pbrfit.fitting.runner.Compiler(clock)
    square = jax.jit(lambda v: v * v)
    x = jnp.arange(3.0)
    compiler.prefetch("square", square, x)
    assert "square" in compiler.pending
    compiler.pending["square"].result()  # compiled while the caller did something else
    np.testing.assert_array_equal(compiler.get("square", square, x)(x), [0.0, 1.0, 4.0])
    assert not compiler.pending and clock["compile_background"] > 0.0 and clock["compile"] >= 0.0
    assert compiler.get("square", None, x) is compiler.done["square"]  # compiled once per key

    @jax.jit
    def bad(v):
        raise RuntimeError("no shape for this")

    compiler.prefetch("bad", bad, x)
    with pytest.raises(RuntimeError, match="no shape for this"):
        compiler.get("bad", bad, x)  # an error in the background thread is raised where the executable is needed
    compiler.prefetch("later", square, jnp.arange(4.0))
    compiler.close()
    assert not compiler.pending and compiler.executor is None
    with jax.enable_x64(True):  # the caller's thread-local setting holds in the compile thread
        wide = pbrfit.fitting.runner.Compiler({})
        x64 = jnp.arange(3.0)
        ones = jax.jit(lambda v: jnp.ones(v.shape))  # float64 only where the trace sees x64 on
        wide.prefetch("ones", ones, x64)
        assert wide.get("ones", ones, x64)(x64).dtype == jnp.float64
        wide.close()
    off = pbrfit.fitting.runner.Compiler({}, background=False)
    off.prefetch("square", square, x)
    assert not off.pending and off.executor is None


def test_small_problems_compile_with_the_options_that_compile_sooner(monkeypatch):
    """A fit program on a problem of fewer than `FAST_COMPILE_ROWS` sample rows (the search:
    `SEARCH_FAST_COMPILE_ROWS`) compiles with `pbrfit.xla.FAST_COMPILE`, ahead of time
    (`Compiler`) or jitted (`fit_jit`), and one on a larger problem with XLA's defaults; both give
    the same start."""
    runner = pbrfit.fitting.runner
    problem = _texel_problem(_checker(4))
    x = jnp.full((16, 5), 0.5, jnp.float32)
    seen = []
    compile_lowered = runner.compile_lowered
    monkeypatch.setattr(runner, "compile_lowered",
                        lambda lowered, options: seen.append(dict(options)) or compile_lowered(lowered, options))
    small = runner.Compiler({}, background=False).get("grid", grid_initialise, x, problem)(x, problem)
    blocks = runner.fit_jit(lambda jac, p: normal_blocks(jac, p))
    jac = jax.jit(pbrfit.fitting.objective.linearize)(x, problem)[1]
    blocks(jac, problem)
    monkeypatch.setattr(runner, "FAST_COMPILE_ROWS", problem.obs.num_rows)  # the same problem, now large
    large = runner.Compiler({}, background=False).get("grid", grid_initialise, x, problem)(x, problem)
    blocks(jac, problem)
    assert seen == [dict(FAST_COMPILE), {}]
    # the coordinate search, which runs slower without XLA's defaults, from fewer rows
    rows = problem.obs.num_rows
    monkeypatch.setattr(runner, "FAST_COMPILE_ROWS", rows + 1)
    monkeypatch.setattr(runner, "SEARCH_FAST_COMPILE_ROWS", rows)
    assert runner.compile_options(grid_initialise, (x, problem)) == dict(FAST_COMPILE)
    assert runner.compile_options(coordinate_search, (x, problem)) == {}
    monkeypatch.setattr(runner, "SEARCH_FAST_COMPILE_ROWS", rows + 1)
    assert runner.compile_options(coordinate_search, (x, problem)) == dict(FAST_COMPILE)
    full, fast = blocks.variants
    assert fast._cache_size() == 1 and full._cache_size() == 1
    np.testing.assert_allclose(small, large, atol=1e-5)


def test_continuation_is_reported_scales_with_the_data_and_is_released(monkeypatch):
    """The prior's weights are relative to the data's curvature (the same fit on images and lights
    four times brighter gives the same maps and 16 times the weights); it acts on the first steps
    only: with a huge weight and one step left the maps are still smoothed, with 45 steps left
    the fit is exact again; with fewer than `RELEASED_STEPS` left there is none."""
    truth = _checker()
    images = _images(VIEWS, truth)
    obs = observations_from_views(VIEWS, images)
    res = fit_observations(obs, resolution=8, max_steps=40, continuation=(0.01, 0.001))
    cont = res.report["continuation"]
    assert cont["relative"] == [0.01, 0.001] and cont["steps"] == SEARCH_AFTER and cont["curvature"] > 0
    assert cont["settle_steps"] == SETTLE_STEPS  # after the search, under the last weight
    np.testing.assert_allclose(cont["weights"], [0.01 * cont["curvature"], 0.001 * cont["curvature"]], rtol=1e-6)
    err = map_rmse(truth, res)
    assert max(err.values()) < 1e-3, err

    bright_views = [dataclasses.replace(v, light_radiance=4.0 * v.light_radiance) for v in VIEWS]
    bright = fit_observations(observations_from_views(bright_views, [4.0 * i for i in images]), resolution=8,
                              max_steps=40, continuation=(0.01, 0.001))
    np.testing.assert_allclose(bright.report["continuation"]["curvature"], 16.0 * cont["curvature"], rtol=1e-3)
    for name in ("base_color", "metallic", "roughness"):
        np.testing.assert_allclose(np.asarray(getattr(bright.material, name)), np.asarray(getattr(res.material, name)),
                                   atol=1e-3)

    short = fit_observations(obs, resolution=8, max_steps=SEARCH_AFTER + RELEASED_STEPS - 1, continuation=(0.01,))
    assert short.report["continuation"] is None
    off = fit_observations(obs, resolution=8, max_steps=SEARCH_AFTER + 1, search=False, continuation=())
    monkeypatch.setattr(pbrfit.fitting.passes, "RELEASED_STEPS", 1)
    # (no uniform check or repair: their re-fits would take more steps)
    held = fit_observations(obs, resolution=8, max_steps=SEARCH_AFTER + 1, search=False, continuation=(10.0,),
                            uniform_check=False, repair=False)
    assert off.report["continuation"] is None and held.report["continuation"]["steps"] == SEARCH_AFTER
    # one released step from a prior ten times the data: the checker's edges are still blurred
    assert map_rmse(truth, off)["base_color"] < 1e-5 < 1e-3 < map_rmse(truth, held)["base_color"]
    released = fit_observations(obs, resolution=8, max_steps=60, search=False, continuation=(10.0,))
    assert max(map_rmse(truth, released).values()) < 1e-3
    with pytest.raises(ValueError, match="continuation"):
        fit_observations(obs, resolution=8, continuation=(-1.0,))


def test_schedule_levels():
    assert schedule((64, 64)) == [(1, 1), (4, 4), (16, 16), (64, 64)]
    assert schedule((8, 8)) == [(1, 1), (8, 8)]


def _bumpy(n=8):
    """The checker material with a smooth tangent-space normal map (tilts up to 17°)."""
    from pbrfit.fitting.parameters import normal_from_slopes

    m = _checker(n)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    slopes = np.stack([0.3 * np.sin(2 * np.pi * i / n + 0.4), 0.3 * np.cos(2 * np.pi * j / n + 0.2)], -1)
    return Material(m.base_color, m.metallic, m.roughness, normal=normal_from_slopes(jnp.asarray(slopes, jnp.float32)))


def test_normal_map_recovered_on_small_scene():
    truth = _bumpy()
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    res = fit_observations(obs, resolution=8, fit=("base_color", "roughness", "normal"), max_steps=60)
    got, want = np.asarray(res.material.normal), np.asarray(truth.normal)
    angle = np.degrees(np.arccos(np.clip(np.sum(got * want, -1), -1.0, 1.0)))
    # Most texels come back to about a degree; a few at the map's edge, where roughness and tilt
    # trade off in the highlights these four views see, stay in a local minimum. Which of them do
    # is decided by the last float bits: scaling the images by 1 ± 1e-7 moved the median between
    # 0.93° and 1.38° and the share within 3° between 67% and 80% (0.67° without the
    # continuation; flat normals: 17°).
    assert np.median(angle) < 1.5 and np.mean(angle < 3.0) > 0.65, angle
    assert map_rmse(truth, res)["base_color"] < 0.03
    assert res.uncertainty.shape == (8, 8, 7) and np.all(np.isfinite(res.uncertainty[..., 5:]))
    # the same images fitted with flat normals leave a clearly worse match
    flat = fit_observations(obs, resolution=8, fit=("base_color", "roughness"), max_steps=60)
    assert flat.report["final_loss"] > 5 * res.report["final_loss"], (flat.report["final_loss"], res.report["final_loss"])


def test_pbrfit_fit_is_the_function():
    """``pbrfit.fit(capture)`` (the Python API) is the fit function whatever was imported before
    it, in a fresh interpreter: the room is `pbrfit.fitting`, so no submodule import can replace
    the package's attribute."""
    import subprocess
    import sys

    code = """
import pbrfit
first = pbrfit.fit
import pbrfit.fitting.api
from pbrfit.fitting.api import FitResult, fit, fit_observations
assert pbrfit.fit is first is fit and callable(pbrfit.fit), pbrfit.fit
assert pbrfit.fitting.api.fit_observations is fit_observations and pbrfit.FitResult is FitResult
assert pbrfit.fitting.solvers.structured.CG_RTOL > 0 and pbrfit.fitting.sharding.pixel_mesh
import inspect, pickle
assert list(inspect.signature(pbrfit.fit).parameters)[0] == "capture"
assert pickle.loads(pickle.dumps(pbrfit.fit)) is pbrfit.fit
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def _noisy_checker_obs(truth, sigma=0.01, seed=0):
    rng = np.random.default_rng(seed)
    return observations_from_views(VIEWS, [i + rng.normal(0, sigma, i.shape).astype(np.float32)
                                           for i in _images(VIEWS, truth)])


def _dense_profile_sigma(obs, res, uniform):
    """σ̂ sqrt(diag(P⁻¹)) of the common values of channels `uniform` of a fit of the 8 × 8 maps
    (every texel seen): P = DᵀHD − DᵀHF (FᵀHF)⁻¹ FᵀHD from the dense H = JᵀJ at the fitted maps,
    D moving those channels of every texel together, F the other channels."""
    problem = dataclasses.replace(_texel_problem(_checker()), obs=obs,
                                  pair_weight=jnp.zeros(len(neighbour_pairs((8, 8)))))
    x = np.asarray(_stack(res.material))
    jac = np.asarray(_dense_jacobian(jnp.asarray(x), problem), np.float64)
    h = jac.T @ jac
    d = np.zeros((len(uniform), 64, 5))
    for i, c in enumerate(uniform):
        d[i, :, c] = 1.0
    d = d.reshape(len(uniform), -1)
    f = np.ones((64, 5), bool)
    f[:, uniform] = False
    f = f.ravel()
    hd = h @ d.T
    p = d @ hd - hd[f].T @ np.linalg.solve(h[np.ix_(f, f)], hd[f])
    return res.report["residual_sigma"] * np.sqrt(np.diag(np.linalg.inv(p)))


def test_uniform_check_makes_an_unsupported_map_one_value():
    """A dielectric under 1% noise: the metallic map fits noise, and base colour follows it
    (diffuse ∝ base · (1 - metallic)); one metallic value fitted from every pixel has no such
    scatter. The checker's roughness contrast (0.35 / 0.45) is far above its noise: it stays a map."""
    truth = _checker()
    obs = _noisy_checker_obs(truth)
    on = fit_observations(obs, resolution=8, max_steps=40)
    off = fit_observations(obs, resolution=8, max_steps=40, uniform_check=False)
    assert off.report["uniform_check"] == dict(skipped=TURNED_OFF)
    check = on.report["uniform_check"]
    metal, rough = check["metallic"], check["roughness"]
    assert metal["uniform"] and metal["statistic"] <= metal["threshold"] == 2 * (64 - 1), check
    assert not rough["uniform"] and rough["wald"] > 4 * rough["threshold"] and "statistic" not in rough, check
    m = np.asarray(on.material.metallic)
    assert np.all(m == np.float32(metal["value"])) and metal["value"] < 0.01
    sigma = np.asarray(on.uncertainty)[..., 3]
    assert np.all(sigma == np.float32(metal["sigma"])) and 0 < metal["sigma"] < 0.01
    # the value's σ against the dense profile curvature (metallic moved, the rest re-fitted)
    np.testing.assert_allclose(metal["sigma"], _dense_profile_sigma(obs, on, [3])[0], rtol=0.02)
    assert metal["converged"] and len(metal["values"]) >= 2, metal  # Newton moved it from the Wald start
    assert len(set(np.asarray(on.material.roughness).ravel().tolist())) > 2  # still a map
    # the steps of the metallic re-fits and of the repair's passes count; the map fit's were 40 at most
    repaired = sum(p.get("steps", 0) for p in on.report["repair"]["passes"])
    assert on.report["steps"] == sum(h["steps"] for h in on.report["levels"]) + metal["steps"] + repaired
    err_on, err_off = map_rmse(truth, on), map_rmse(truth, off)
    assert err_on["metallic"] < 0.5 * err_off["metallic"] and err_on["base_color"] < err_off["base_color"], (
        err_on, err_off)


def test_uniform_check_finds_one_roughness_and_keeps_a_binary_metallic_map(monkeypatch):
    """Uniform roughness and metallic under noise both become one value, near the truth; a
    metal half beside a dielectric half is kept as a map without a re-fit (its Wald statistic
    alone), with the same steps and maps as without the check."""
    base = _checker().base_color
    truth = Material(base, jnp.zeros((8, 8, 1)), jnp.full((8, 8, 1), 0.4))
    obs = _noisy_checker_obs(truth, seed=1)
    res = fit_observations(obs, resolution=8, max_steps=40)
    check = res.report["uniform_check"]
    metal, rough = check["metallic"], check["roughness"]
    assert metal["uniform"] and rough["uniform"], check
    # measured: metallic 0.0003 (σ 0.0010), roughness 0.3995 (σ 0.0014)
    assert metal["value"] < 2 * metal["sigma"] and abs(rough["value"] - 0.4) < 4 * rough["sigma"], check
    # both σ from the 2 × 2 profile matrix of the two common values, against its dense form
    np.testing.assert_allclose([metal["sigma"], rough["sigma"]], _dense_profile_sigma(obs, res, [3, 4]), rtol=0.02)
    np.testing.assert_array_equal(np.asarray(res.material.roughness), np.float32(rough["value"]))
    assert map_rmse(truth, res)["base_color"] < 0.01

    half = np.zeros((8, 8, 1), np.float32)
    half[:, :4] = 1.0
    truth = Material(base, jnp.asarray(half), _checker().roughness)
    obs = _noisy_checker_obs(truth, seed=1)
    res = fit_observations(obs, resolution=8, max_steps=40)
    off = fit_observations(obs, resolution=8, max_steps=40, uniform_check=False)
    check = res.report["uniform_check"]
    for name in ("metallic", "roughness"):
        assert not check[name]["uniform"] and check[name]["wald"] > 4 * check[name]["threshold"], check
        assert "statistic" not in check[name] and "steps" not in check[name], check
    assert res.report["steps"] == off.report["steps"]
    for name in ("base_color", "metallic", "roughness"):
        np.testing.assert_array_equal(np.asarray(getattr(res.material, name)), np.asarray(getattr(off.material, name)))
    np.testing.assert_array_equal(np.asarray(res.uncertainty), np.asarray(off.uncertainty))
    assert map_rmse(truth, res)["metallic"] < 0.03  # measured 0.013
    # re-fitted anyway, the common value loses by far and the map fit is returned as it was
    monkeypatch.setattr(pbrfit.fitting.stages.selection, "WALD_MARGIN", np.inf)
    forced = fit_observations(obs, resolution=8, max_steps=40)
    metal = forced.report["uniform_check"]["metallic"]
    assert not metal["uniform"] and metal["statistic"] > 10 * metal["threshold"] and metal["steps"] > 0, metal
    refits = sum(forced.report["uniform_check"][name]["steps"] for name in ("metallic", "roughness"))
    assert forced.report["steps"] == off.report["steps"] + refits  # the rejected re-fits' steps count
    for name in ("base_color", "metallic", "roughness"):
        np.testing.assert_array_equal(np.asarray(getattr(forced.material, name)),
                                      np.asarray(getattr(off.material, name)))
    np.testing.assert_array_equal(np.asarray(forced.uncertainty), np.asarray(off.uncertainty))


def test_uniform_check_says_why_it_was_skipped():
    skipped = pbrfit.fitting.stages.selection.uniform_check_skipped
    on = np.array([1, 1, 1, 1, 1], np.float32)
    assert skipped("structured", "l2", 0.0, (8, 8), on) is None
    assert skipped("structured", "l2", 0.0, (1, 1), on) == "a uniform material"
    assert skipped("lm", "l2", 0.0, (8, 8), on) == "needs the structured solver"
    assert "l2 loss" in skipped("structured", "cauchy", 0.0, (8, 8), on)
    assert "smoothness prior" in skipped("structured", "l2", 0.1, (8, 8), on)
    assert skipped("structured", "l2", 0.0, (8, 8), np.array([1, 1, 1, 0, 0], np.float32)) == (
        "neither metallic nor roughness is fitted")


def test_uniform_check_leaves_unseen_texels_at_the_prior():
    """A uniform roughness seen on part of the map: the seen texels get the common value, the
    unseen ones keep the prior (0.5) and σ = +inf, as in any fit."""
    truth = Material(_checker().base_color, jnp.zeros((8, 8, 1)), jnp.full((8, 8, 1), 0.4))
    half = _views(2, extent=2.0)  # the plane covers only the centre of uv
    rng = np.random.default_rng(2)
    obs = observations_from_views(half, [i + rng.normal(0, 0.01, i.shape).astype(np.float32)
                                         for i in _images(half, truth)])
    res = fit_observations(obs, resolution=8, max_steps=20)
    rough = res.report["uniform_check"]["roughness"]
    seen = res.coverage > 0
    assert rough["uniform"] and seen.any() and (~seen).any(), rough
    r, sigma = np.asarray(res.material.roughness)[..., 0], np.asarray(res.uncertainty)[..., 4]
    assert np.all(r[seen] == np.float32(rough["value"])) and np.all(r[~seen] == 0.5)
    assert np.all(np.isfinite(sigma[seen])) and np.all(np.isinf(sigma[~seen]))


def _patches(seed, n=8, patch=2):
    """Random (base colour, roughness) patches of patch × patch texels, metallic 0."""
    rng = np.random.default_rng(seed)
    m = n // patch
    rough = np.kron(rng.uniform(0.08, 0.9, (m, m)), np.ones((patch, patch)))[..., None]
    base = np.kron(rng.uniform(0.05, 0.9, (m, m, 3)), np.ones((patch, patch, 1)))
    return Material(jnp.asarray(base, jnp.float32), jnp.zeros((n, n, 1)), jnp.asarray(rough, jnp.float32))


def test_repair_restarts_a_cluster_left_in_a_wrong_basin():
    """Patches of random roughness, noiseless: without the repair the fit ends with a cluster of
    texels in a wrong basin (roughness RMSE 0.13 when written; asserted > 0.05); the repair flags
    it, restarts it from its neighbours and the fit ends exact (two misfit passes take the
    objective from 0.044 to 7e-6, the outlier pass to 1e-12, when written). Every pass's report
    adds up."""
    truth = _patches(10)
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    plain = fit_observations(obs, resolution=8, max_steps=40, repair=False)
    assert plain.report["repair"] == dict(skipped=TURNED_OFF) and map_rmse(truth, plain)["roughness"] > 0.05
    res = fit_observations(obs, resolution=8, max_steps=40)
    err = map_rmse(truth, res)
    assert err["roughness"] < 1e-4 and err["base_color"] < 1e-4 and err["metallic"] < 1e-4, err
    passes = res.report["repair"]["passes"]
    # every stage after the solve has one summary, in the order they ran
    assert [s["name"] for s in res.report["stages"]] == ["repair", "uniform_check", "unconstrained"]
    repair = res.report["stages"][0]
    assert repair["ran"] and repair["skipped"] is None and repair["seconds"] > 0
    assert repair["steps"] == sum(p["steps"] for p in passes) > 0
    off = plain.report["stages"][0]
    assert off == dict(name="repair", ran=False, skipped=TURNED_OFF, seconds=off["seconds"], steps=0)
    first = passes[0]
    assert first["kept"] and first["flagged"] > 0 and first["moved"] >= first["flagged"]
    assert first["energy_after"] < 1e-2 * first["energy_before"]
    assert first["clusters_kept"] == first["clusters"] and first["texels_kept"] == first["moved"]
    ran = [p for p in passes if p["flagged"] > 0]

    def checks(report):  # the uniform check's re-fits, also counted in "steps"
        return sum(c.get("steps", 0) for c in report["uniform_check"].values() if isinstance(c, dict))

    assert res.report["steps"] - checks(res.report) == (plain.report["steps"] - checks(plain.report)
                                                         + sum(p["steps"] for p in ran))
    # misfit passes, then one outlier pass; a misfit pass runs only after a kept one that gained > 1%
    assert [p["kind"] for p in passes] == ["misfit"] * (len(passes) - 1) + ["outliers"]
    misfit = [p for p in ran if p["kind"] == "misfit"]
    for before, after in zip(misfit, misfit[1:]):
        assert before["kept"] and after["energy_before"] == before["energy_after"]
        assert before["energy_before"] - before["energy_after"] > REPAIR_PROGRESS * before["energy_before"]
    kept = [p for p in ran if p["kept"]]
    for before, after in zip(kept, kept[1:]):
        assert after["energy_before"] == before["energy_after"]
    for p in ran:
        assert p["kept"] == (p["energy_after"] < p["energy_before"] and p["clusters_kept"] > 0)
        assert p["kept"] or p["clusters_kept"] == p["texels_kept"] == 0


def test_repair_outlier_pass_finds_a_cluster_the_misfit_misses(monkeypatch):
    """Under noise a wrong basin's misfit hides in the noise; with the misfit test blinded, the
    outlier pass alone finds the cluster of seed 10's patches (out of line with the patch around
    it), restarts it and the fit becomes exact."""
    truth = _patches(10)
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    monkeypatch.setattr(pbrfit.fitting.stages.repair, "misfit_texels", lambda mean, count, seen, scale: np.zeros(len(seen), bool))
    res = fit_observations(obs, resolution=8, max_steps=40)
    err = map_rmse(truth, res)
    assert err["roughness"] < 1e-3 and err["base_color"] < 1e-3, err
    (p,) = res.report["repair"]["passes"]
    assert p["kind"] == "outliers" and p["flagged"] > 0 and p["kept"]
    assert p["energy_after"] < 1e-2 * p["energy_before"]


def test_repair_puts_back_the_clusters_judged_no_better(monkeypatch):
    """With the rim of the moved region judged no better, its texels keep the solve's values, the
    inner ones keep the repair's, and the linearisation the fit goes on with is the merged
    point's: the reported loss is the objective at the returned maps."""
    truth = _patches(10)
    obs = observations_from_views(VIEWS, _images(VIEWS, truth))
    plain = fit_observations(obs, resolution=8, max_steps=40, repair=False, uniform_check=False)
    judged = {}

    def half(moving, before, after, index, weight, samples, margin=0.0, spread=0.0, dof=None):
        # the moved region's inner texels judged better, its rim (the flagged texels' unflagged
        # neighbours, mostly) put back
        moving = np.asarray(moving, bool)
        inner = ndimage.minimum_filter(moving[:64].reshape(8, 8), size=3, mode="wrap").reshape(-1)
        better = moving & np.concatenate([inner, np.zeros(moving.size - 64, bool)])
        judged.update(moving=moving, better=better)
        return better, 2, 1

    monkeypatch.setattr(pbrfit.fitting.stages.repair, "improved_clusters", half)
    monkeypatch.setattr(pbrfit.fitting.stages.repair, "REPAIR_PASSES", 1)
    monkeypatch.setattr(pbrfit.fitting.stages.repair, "outlier_texels", lambda x, channels, trusted, shape: np.zeros(64, bool))
    res = fit_observations(obs, resolution=8, max_steps=40, uniform_check=False)
    p, last = res.report["repair"]["passes"]
    assert last == dict(kind="outliers", flagged=0)
    better, moving = judged["better"][:64], judged["moving"][:64]
    assert better.any() and (moving & ~better).any()
    x0, x = np.asarray(_stack(plain.material)), np.asarray(_stack(res.material))
    np.testing.assert_array_equal(x[~better], x0[~better])
    assert p["clusters"] == 2 and p["clusters_kept"] == 1 and p["kept"]  # the loss fell 160-fold when written
    assert p["texels_kept"] == better.sum() and not np.array_equal(x[better], x0[better])
    energy = float(jax.jit(objective)(jnp.asarray(x), _texel_problem(truth)))
    np.testing.assert_allclose(res.report["final_loss"], energy, rtol=1e-3)


def test_models_on_a_capture_without_an_environment(tmp_path):
    """Under punctual lights alone: multiscatter reads the BRDF tables built without an
    environment (`pbrfit.lighting.ibl.brdf_tables`), in `render_capture` and `fit`; a model that shades an
    environment is refused at once, as are a capture that is not one and a NaN material."""
    from _capture_fixtures import base_capture_dict, write_capture

    from pbrfit.scene.capture import load_capture
    from pbrfit.render.views import render_capture

    data = base_capture_dict()
    del data["environment"]
    root = write_capture(tmp_path / "cap", data)
    capture = load_capture(root)
    material = Material.uniform((0.9, 0.9, 0.9), 0.0, 0.6, size=2)
    (plain, alpha), _ = render_capture(root, material)  # a folder, as fit takes
    (multi, _), _ = render_capture(capture, material, model=Model(multiscatter=True))
    lit = (alpha > 0) & (plain.sum(-1) > 1e-3)
    gain = multi[lit] / plain[lit]
    assert np.all(gain >= 1.0 - 1e-6) and 1.0 < gain.max() < 1.2  # compensation adds what masking lost
    result = pbrfit.fit(capture, maps="none", model=Model(multiscatter=True), max_steps=2)
    assert result.report["model"]["multiscatter"] and np.isfinite(result.report["final_loss"])
    for call, match in ((lambda: render_capture(capture, material, model=Model(ibl="split_sum")), "has none"),
                        (lambda: pbrfit.fit(capture, model=Model(ibl="split_sum")), "shades an environment light"),
                        (lambda: pbrfit.fit(capture, model=Model(ibl="monte_carlo")), "reference integrator"),
                        (lambda: pbrfit.fit(capture, model="ggx"), "expected a pbrfit.Model"),
                        (lambda: pbrfit.fit(42), "expected a pbrfit.scene.capture.Capture or a capture folder, got int"),
                        (lambda: pbrfit.fit(capture, views=[1, 2]), r"views: expected one pbrfit.render.shade.ViewInputs per frame \(2\)"),
                        (lambda: pbrfit.fit(tmp_path / "none", pixel_samples=9), "pixel_samples must be 'auto' or"),
                        (lambda: render_capture(capture, Material.uniform((0.5,) * 3, float("nan"), 0.5)),
                         "metallic map holds NaN")):
        with pytest.raises(ValueError, match=match):
            call()
    # a folder whose mesh has no uv: refused when any map of the material is more than one texel
    from _capture_fixtures import write_quad_obj

    from pbrfit.errors import CaptureError

    write_quad_obj(root / "mesh.obj", uv=False)
    one = Material.uniform((0.5,) * 3, 0.0, 0.5)
    assert len(render_capture(root, one)) == 2
    with pytest.raises(CaptureError, match="no texture coordinates"):
        render_capture(root, dataclasses.replace(one, roughness=jnp.full((2, 2, 1), 0.5)))


def test_residual_variance_under_a_prior_is_the_pixels_alone():
    """σ̂² counts the pixels' residuals, not the prior's energy: with --smooth the report's
    residual σ (and every standard error with it) grew with the prior's weight."""
    obs = _noisy_checker_obs(_checker(), sigma=0.02)
    res = fit_observations(obs, resolution=8, max_steps=20, smooth=1.0)
    d = np.concatenate([(im - tg)[m] for im, tg, m in zip(res.images, res.targets, res.masks)]).astype(np.float64)
    n_par = res.report["observed_texels"] * len(res.report["fitted"])
    pixels_only = math.sqrt(np.sum(d * d) / (d.size - n_par))
    assert res.report["residual_sigma"] == pytest.approx(pixels_only, rel=1e-3)


def test_occlusion_of_a_sphere_on_a_floor(tmp_path):
    """A sphere on a floor under a sky: "auto" finds the shadows, casts the rays (cached with the
    G-buffers) and the split sum fits with its occlusion factors (a coarse cell grid: the
    wiring is the subject, `tests/lighting/test_visibility.py` checks the values)."""
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.lighting.visibility import OcclusionSettings
    from pbrfit.scene.capture import load_capture

    synthesize(make_scene("sphere-floor", size=16, views=2, texture_size=8), tmp_path / "cap")
    cache = tmp_path / "cache"
    res = pbrfit.fit(load_capture(tmp_path / "cap"), maps="none", max_steps=2, repair=False, uniform_check=False,
                     ibl="split_sum", occlusion="auto", occlusion_settings=OcclusionSettings(rows=4, probe_points=128), cache_dir=cache)
    occlusion = res.report["occlusion"]
    assert occlusion["mode"] == "auto" and occlusion["used"] and occlusion["probed_share"] > 0.01
    assert occlusion["cells"] > 0 and occlusion["rows"] > 0 and occlusion["seconds"] > 0
    assert all(np.isfinite(res.report["psnr"]))
    assert len(list(cache.glob("visibility-*.npy"))) == 1
