"""The fit's pictures (`pbrfit.io.pictures`): contact sheets and maps.png, drawn at a readable size,
labelled, with one stated error scale."""

from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from _capture_fixtures import write_quad_glb
from pbrfit.io.outputs import write_fit_output
from pbrfit.io.pictures import (_BAR, _LABEL, _PAD, ERROR_FLOOR, MAP_SCALE, MIN_PANEL, NO_VALUE, colormap,
                                contact_sheet, enlarge, error_scale, maps_sheet)
from pbrfit.physics.material import Material
from pbrfit.scene.mesh import load_mesh


def _rgb8(x):
    return np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)


def _panel(sheet, row, column, shape, row_height=None):
    """The panel at (row, column) of a sheet whose panels are `shape` (h, w)."""
    h, w = shape
    y = _PAD + row * ((row_height or h) + _LABEL + _PAD) + _LABEL
    x = _PAD + column * (w + _PAD)
    return sheet[y:y + h, x:x + w]


def _view(h=12, w=20, error=0.0, seed=0):
    rng = np.random.default_rng(seed)
    target = rng.uniform(0.2, 0.8, (h, w, 3)).astype(np.float32)
    mask = np.zeros((h, w), bool)
    mask[2:-2, 3:-3] = True
    return target, target + np.float32(error), mask


def test_colormap_runs_dark_to_light():
    rgb = colormap(np.linspace(0, 1, 33))
    lightness = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    assert np.all(np.diff(lightness) > 0) and lightness[0] < 0.02 and lightness[-1] > 0.9
    np.testing.assert_array_equal(colormap(np.array([-1.0, 2.0, np.nan])), colormap(np.array([0.0, 1.0, 0.0])))


def test_enlarge_by_the_least_whole_factor_nearest_neighbour():
    small = np.arange(12, dtype=np.float32).reshape(3, 4, 1)
    big = enlarge(small)
    assert big.shape == (258, 344, 1)  # k = ceil(256 / 3) = 86
    np.testing.assert_array_equal(big[::86, ::86], small)
    np.testing.assert_array_equal(big[85::86, 85::86], small)  # each pixel a block of its own value
    assert enlarge(np.zeros((300, 400, 3))).shape == (300, 400, 3)  # large enough: as it is


def test_contact_sheet_size_labels_and_bar():
    target, fitted, mask = _view(error=0.05)
    sheet = contact_sheet(target, fitted, mask, True, scale=0.1, title="view 000")
    k = -(-MIN_PANEL // 12)  # 22: the short side, 12 px, enlarged to at least 256
    shape = (12 * k, 20 * k)
    assert sheet.dtype == np.uint8 and sheet.shape[0] >= shape[0] + _LABEL and sheet.shape[1] >= 3 * shape[1] + _BAR
    np.testing.assert_array_equal(_panel(sheet, 0, 0, shape), _rgb8(enlarge(target)))  # the target, shown as is
    np.testing.assert_array_equal(_panel(sheet, 0, 1, shape), _rgb8(enlarge(fitted)))
    heat = _panel(sheet, 0, 2, shape)
    np.testing.assert_array_equal(heat[k * 6, k * 10], _rgb8(colormap(np.array(0.5))))  # 0.05 of 0.1
    np.testing.assert_array_equal(heat[0, 0], _rgb8(np.array(NO_VALUE)))  # outside the mask
    # labels: the band above each panel holds dark text; the bar right of the panels is the colour map
    for column in range(3):
        band = sheet[_PAD:_PAD + _LABEL, _PAD + column * (shape[1] + _PAD):][:, :shape[1]]
        assert band.min() < 100, column
    bar_x = _PAD + 3 * (shape[1] + _PAD)
    bar = sheet[_PAD + _LABEL:_PAD + _LABEL + shape[0], bar_x + _BAR // 2]
    np.testing.assert_allclose(bar[1].astype(int), _rgb8(colormap(np.array(1.0))), atol=6)  # top: the scale
    np.testing.assert_allclose(bar[-2].astype(int), _rgb8(colormap(np.array(0.0))), atol=6)  # bottom: 0
    ticks = sheet[_PAD + _LABEL:_PAD + _LABEL + shape[0], bar_x + _BAR + 5:]
    assert ticks.min() < 100  # tick labels drawn
    assert sheet[-2 * _PAD - 10:-_PAD, _PAD:400].min() < 100  # the note of the units under the panels


def test_error_scale_is_one_for_every_view():
    small, large = _view(error=0.01, seed=1), _view(error=0.1, seed=2)
    targets, renders, masks = zip(*[(t, f, m) for t, f, m in (small, large)])
    scale = error_scale(targets, renders, masks)
    assert scale == pytest.approx(0.1, rel=1e-5)  # the larger view's error sets the 99th percentile
    assert error_scale(targets[:1], renders[:1], masks[:1]) < scale / 5  # the small view alone would be scaled up
    sheets = [contact_sheet(t, f, m, True, scale) for t, f, m in zip(targets, renders, masks)]
    assert sheets[0].shape == sheets[1].shape
    shape = (264, 440)
    bar_x = _PAD + 3 * (shape[1] + _PAD)
    np.testing.assert_array_equal(sheets[0][:, bar_x:], sheets[1][:, bar_x:])  # the same bar and ticks
    inside = enlarge(masks[0][..., None])[..., 0]
    heat = [_panel(s, 0, 2, shape)[inside].astype(float).mean() for s in sheets]
    assert heat[0] < heat[1] - 50  # the small error shows dark on the shared scale
    # an exact fit is not magnified: the floor (a fraction of the mean target) keeps it black
    t, _, m = _view()
    exact = t + np.float32(1e-7)
    assert error_scale([t], [exact], [m]) == pytest.approx(ERROR_FLOOR * t[m].mean(), rel=1e-4)
    sheet = contact_sheet(t, exact, m, True, error_scale([t], [exact], [m]))
    assert _panel(sheet, 0, 2, shape)[inside].max() <= _rgb8(colormap(np.array(0.01))).max()


def _material(h=4, w=4, offset=0.0):
    grid = np.linspace(0.2, 0.7, h * w, dtype=np.float32).reshape(h, w, 1)
    return Material(np.repeat(grid, 3, -1) + offset, grid + offset, 1.0 - grid + offset)


def test_write_fit_output_pictures_with_and_without_truth(tmp_path):
    capture = SimpleNamespace(mesh=load_mesh(write_quad_glb(tmp_path / "quad.glb")), world_up="+y",
                              frames=[SimpleNamespace(color_space="srgb")] * 2)
    fit = _material()
    sigma = np.full((4, 4, 5), 0.05, np.float32)
    coverage = np.ones((4, 4), np.float32)
    coverage[0] = 0  # a row no view sees
    sigma[0] = np.inf
    small, large = _view(error=0.01, seed=1), _view(error=0.1, seed=2)
    views = dict(targets=[(t, m) for t, _, m in (small, large)], renders=[f for _, f, _ in (small, large)])
    plain = write_fit_output(tmp_path / "plain", capture, fit, sigma, coverage, {}, **views)
    truth = write_fit_output(tmp_path / "truth", capture, fit, sigma, coverage, {}, truth=_material(offset=0.05),
                             **views)
    panel = (256, 256)  # 4 texels enlarged 64 times
    without = np.asarray(Image.open(plain / "maps.png").convert("RGB"))
    with_truth = np.asarray(Image.open(truth / "maps.png").convert("RGB"))
    assert without.shape[0] == with_truth.shape[0] >= 3 * (panel[0] + _LABEL)  # base colour, metallic, roughness
    for sheet, columns in ((without, 2), (with_truth, 4)):  # fit and sigma; with the truth, truth and error too
        bar_x = _PAD + columns * (panel[1] + _PAD) + _BAR // 2
        np.testing.assert_allclose(sheet[_PAD + _LABEL + 1, bar_x].astype(int), _rgb8(colormap(np.array(1.0))), atol=6)
    for sheet in (without, with_truth):
        roughness_sigma = _panel(sheet, 2, 1, panel)
        np.testing.assert_allclose(roughness_sigma[-1, -1].astype(int), _rgb8(colormap(np.array(0.05 / MAP_SCALE))), atol=1)
        np.testing.assert_array_equal(roughness_sigma[0, 0], _rgb8(np.array(NO_VALUE)))  # unseen
    np.testing.assert_array_equal(_panel(with_truth, 1, 2, panel)[-1, 0], _rgb8(np.array(0.2 + 12 * 0.5 / 15 + 0.05)))
    error = _panel(with_truth, 1, 3, panel)
    np.testing.assert_allclose(error[-1, -1].astype(int), _rgb8(colormap(np.array(0.05 / MAP_SCALE))), atol=1)
    # the contact sheets of both views are written on one scale: the same colour bar
    a, b = (np.asarray(Image.open(plain / "views" / f"{k:03d}.png").convert("RGB")) for k in (0, 1))
    bar_x = _PAD + 3 * (440 + _PAD)
    assert a.shape == b.shape and min(a.shape[:2]) >= MIN_PANEL
    np.testing.assert_array_equal(a[:, bar_x:], b[:, bar_x:])
    with pytest.raises(ValueError, match="truth base_color is \\(2, 2\\), the fit \\(4, 4\\)"):
        maps_sheet(fit, sigma, coverage, _material(2, 2))


def test_maps_sheet_normal_row_angle_to_truth():
    """With normals fitted, a fourth row: the normal, and against a true normal the angle between
    them, on the shared bar read as a fraction of 90 degrees."""
    tilt = np.radians(4.5)  # half the bar: 0.05 of 90 degrees
    up = np.zeros((4, 4, 3), np.float32)
    up[..., 2] = 1.0
    tilted = np.zeros_like(up)
    tilted[..., 0], tilted[..., 2] = np.sin(tilt), np.cos(tilt)
    base = _material()
    fit = Material(base.base_color, base.metallic, base.roughness, normal=up)
    truth = Material(base.base_color, base.metallic, base.roughness, normal=tilted)
    sheet = maps_sheet(fit, np.full((4, 4, 5), 0.01, np.float32), np.ones((4, 4)), truth)
    panel = (256, 256)
    assert sheet.shape[0] >= 4 * (panel[0] + _LABEL)
    np.testing.assert_array_equal(_panel(sheet, 3, 0, panel)[0, 0], _rgb8(np.array([0.5, 0.5, 1.0])))
    np.testing.assert_allclose(_panel(sheet, 3, 3, panel)[0, 0].astype(int), _rgb8(colormap(np.array(0.5))), atol=1)
    without = maps_sheet(fit, np.full((4, 4, 5), 0.01, np.float32), np.ones((4, 4)))
    assert without.shape[0] >= 4 * (panel[0] + _LABEL) and without.shape[1] < sheet.shape[1]
