"""The default's choice of the environment light's model (`pbrfit.fitting.stages.ibl`), and of
the light reflected between surfaces with per-pixel integrals (the bounce; on a Mitsuba capture
with that light: `tests/test_synth_mitsuba.py`)."""

import numpy as np
import pytest

from pbrfit.fitting.options import FitOptions, occlusion_mode
from pbrfit.fitting.stages import ibl as ibl_stage
from pbrfit.fitting.stages.ibl import (MISFIT_SHARE, misfit_evidence, per_pixel_explains_better,
                                       split_sum_misfits)


def _views(residual, level=0.5, masked=0):
    """(images, targets, masks) of two 32 × 32 views whose targets are the images plus ``residual``
    (a function of the view's index and its (H, W) grid), ``masked`` border pixels left out."""
    images, targets, masks = [], [], []
    y, x = np.mgrid[0:32, 0:32] / 32.0
    for k in range(2):
        image = np.full((32, 32, 3), level) + 0.1 * x[..., None]
        mask = np.zeros((32, 32), bool)
        mask[masked:32 - masked, masked:32 - masked] = True
        images.append(image)
        targets.append(image + residual(k, y, x))
        masks.append(mask)
    return images, targets, masks


def test_misfit_evidence_tells_a_smooth_misfit_from_noise():
    """A residual that changes slowly over the image (a lighting model's error) is shared by
    neighbours: correlation near 1 and a share near its RMS over the mean value; white noise of
    the same size shows none; a perfect fit shows nothing at all."""
    rng = np.random.default_rng(0)
    smooth = lambda k, y, x: (0.1 * np.sin(3 * x + k) * np.cos(2 * y))[..., None] * np.ones(3)  # noqa: E731
    noise = lambda k, y, x: 0.05 * rng.standard_normal((32, 32, 3))  # noqa: E731
    shared = misfit_evidence(*_views(smooth, masked=2))
    assert shared["rho"] > 0.9 and shared["z"] > 50 and split_sum_misfits(shared)
    rms = np.sqrt(np.mean(np.concatenate([(t - i)[m] for i, t, m in zip(*_views(smooth, masked=2))]) ** 2))
    level = np.mean(np.concatenate([t[m] for _, t, m in zip(*_views(smooth, masked=2))]))
    assert shared["share"] == pytest.approx(rms / level, rel=0.05)
    white = misfit_evidence(*_views(noise))
    assert abs(white["rho"]) < 0.05 and white["share"] < MISFIT_SHARE / 2 and not split_sum_misfits(white)
    assert misfit_evidence(*_views(lambda k, y, x: 0.0)) == dict(rho=0.0, z=0.0, share=0.0, pairs=2 * 3 * 2 * 32 * 31)
    # a share below the threshold (a small smooth misfit) is left to the split sum
    small = misfit_evidence(*_views(lambda k, y, x: 0.1 * smooth(k, y, x)))
    assert small["rho"] > 0.9 and not split_sum_misfits(small)
    # no two neighbours fitted: no evidence
    lone = misfit_evidence([np.ones((3, 3, 3))], [np.zeros((3, 3, 3))], [np.eye(3, dtype=bool)])
    assert lone == dict(rho=0.0, z=0.0, share=0.0, pairs=0)


def test_the_likelier_light_model_is_kept_and_occlusion_follows_it():
    assert ibl_stage.per_pixel_skipped(ibl_stage.AUTO_MAX_IBL_PIXELS) is None
    assert "--ibl per_pixel" in ibl_stage.per_pixel_skipped(ibl_stage.AUTO_MAX_IBL_PIXELS + 1)
    # with an estimated noise level, the first (unweighted) fits are compared
    weighted = dict(residual_sigma=0.5, noise_level=dict(first_fit=dict(residual_sigma=0.02)))
    assert ibl_stage.fit_sigma(weighted) == 0.02
    assert per_pixel_explains_better(dict(residual_sigma=0.03), weighted)  # not by the weighted 0.5
    assert per_pixel_explains_better(dict(residual_sigma=0.02), dict(residual_sigma=0.01))
    assert not per_pixel_explains_better(dict(residual_sigma=0.01), dict(residual_sigma=0.01))
    # occlusion, unless asked: auto with per-pixel integrals, off with the split sum
    assert FitOptions().ibl == "auto" and FitOptions().occlusion is None
    assert occlusion_mode(None, "per_pixel") == "auto" and occlusion_mode(None, "split_sum") == "off"
    assert occlusion_mode("on", "split_sum") == "on" and occlusion_mode("off", "per_pixel") == "off"
    with pytest.raises(ValueError, match="ibl must be one of auto, split_sum, per_pixel"):
        FitOptions(ibl=None)


def test_auto_fits_a_path_traced_light_with_per_pixel_integrals(tmp_path, monkeypatch):
    """A sphere on a floor under a sun, its environment light rendered by the Monte Carlo
    reference (with the sphere's shadow): the split sum's fit leaves residuals neighbours share,
    the fit runs again with per-pixel integrals and occlusion auto (which casts the shadow), and
    keeps that fit, whose residuals are the smaller; the split sum's fit counts as "ibl_probe"."""
    import pbrfit
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.lighting.pixel_ibl import PixelIBLSettings

    scene = make_scene("sphere-floor", size=20, views=3, texture_size=8, noise=0.0)
    synthesize(scene.replace(model=scene.model.replace(ibl="monte_carlo"), mc_samples=256), tmp_path / "cap")
    options = dict(resolution=8, pixel_samples=1, search=False, repair=False, uniform_check=False,
                   pixel_ibl_settings=PixelIBLSettings(samples=64, levels=5), cache_dir=tmp_path / "cache")
    # more pixels than "auto" integrates unasked: the split sum is kept, and the choice says why
    monkeypatch.setattr(ibl_stage, "AUTO_MAX_IBL_PIXELS", 100)
    report = pbrfit.fit(tmp_path / "cap", **dict(options, pixel_samples="auto")).report
    capped = report["ibl"]
    assert capped["mode"] == "split_sum" and not capped["choice"]["tried"], capped
    assert "pixel rows to integrate > AUTO_MAX_IBL_PIXELS (100)" in capped["choice"]["skipped"]
    # the linear images' footprint test ran all the same (the light's cap is not the footprint's)
    assert "evidence" in report["footprint"] and "AUTO_MAX_IBL" not in report["footprint"].get("skipped", ""), \
        report["footprint"]
    monkeypatch.undo()
    result = pbrfit.fit(tmp_path / "cap", **options)
    report = result.report
    choice = report["ibl"]["choice"]
    assert choice["tried"] and choice["evidence"]["share"] > 0.05 and choice["evidence"]["rho"] > 0.3, choice
    assert report["ibl"]["mode"] == "per_pixel" and report["model"]["ibl"] == "per_pixel"
    assert choice["residual_sigma"]["per_pixel"] < 0.9 * choice["residual_sigma"]["split_sum"], choice
    assert report["occlusion"]["mode"] == "auto" and report["occlusion"]["used"]
    # with the blocked directions bringing the light the images show where they land, the fit
    # explains these images no better than with them dark (the Monte Carlo reference renders
    # direct light only), and "auto" keeps the dark fit
    bounce = report["occlusion"]["bounce"]
    assert bounce["mode"] == "auto" and bounce["rays"] > 0 and 0 < bounce["unseen_hits"] < 1, bounce
    sigma = bounce["residual_sigma"]
    assert not bounce["used"] and sigma["bounce"] > (1 - ibl_stage.BOUNCE_MIN_GAIN) * sigma["dark"], bounce
    assert report["times"]["bounce_probe"] > 0
    assert 0 < report["times"]["ibl_probe"] < report["wall_time"]


def test_auto_chooses_only_the_light_model_it_derived():
    """"auto" tries per-pixel integrals only for the capture's own split-sum model: not for a
    `Model` or a model mapping with ``ibl`` the caller gave, not with fitted normals (which
    per-pixel integrals hold fixed), not where the option names a mode."""
    from pbrfit.fitting.api import _chooses_ibl
    from pbrfit.physics.model import Model

    split = Model(ibl="split_sum")
    assert _chooses_ibl(FitOptions(), split)
    assert _chooses_ibl(FitOptions(model={"diffuse": "burley"}), split)
    assert not _chooses_ibl(FitOptions(), Model(ibl=None))  # no environment
    assert not _chooses_ibl(FitOptions(ibl="split_sum"), split)
    assert not _chooses_ibl(FitOptions(model=split), split)
    assert not _chooses_ibl(FitOptions(model={"ibl": "split_sum"}), split)
    assert not _chooses_ibl(FitOptions(fit=("base_color", "roughness", "normal")), split)
