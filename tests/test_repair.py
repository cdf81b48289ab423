"""The basin repair's host-side pieces (`pbrfit.repair`); the whole repair is tested in test_fit."""

import numpy as np

from pbrfit.repair import fill_from_nearest, misfit_texels, texel_misfit


def test_texel_misfit_means_each_texels_reading_rows():
    # 3 pixels, 1 sample each; pixel 0 reads texels 0 and 1, pixel 1 texel 1, pixel 2 texel 2 (weight 0 on 3)
    r = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 3.0]])
    index = np.array([[0, 1, 0, 0], [1, 1, 1, 1], [2, 3, 3, 3]])
    weight = np.array([[0.5, 0.5, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    mean, count = texel_misfit(r, index, weight, 1, 4)
    np.testing.assert_allclose(mean, [1.0, 2.5, 9.0, 0.0])
    np.testing.assert_array_equal(count, [1, 2, 1, 0])


def test_misfit_texels_flags_outliers_over_the_median_and_floor():
    mean = np.array([1.0, 1.1, 0.9, 50.0, 1.0, 80.0])
    count = np.array([5, 5, 5, 5, 5, 0])
    seen = np.array([True, True, True, True, True, True])
    np.testing.assert_array_equal(misfit_texels(mean, count, seen, scale=1.0),
                                  [False, False, False, True, False, False])
    # an exact fit: everything below the floor, nothing flagged
    assert not misfit_texels(mean * 1e-16, count, seen, scale=1.0).any()


def test_fill_from_nearest_copies_free_channels_of_the_nearest_source():
    x = np.arange(9 * 2, dtype=np.float32).reshape(9, 2)
    flagged = np.zeros(9, bool)
    flagged[[4, 5]] = True
    sources = np.ones(9, bool)
    sources[8] = False  # unseen: never a source
    free = np.ones((9, 2), np.float32)
    free[:, 1] = 0  # channel 1 held
    y = fill_from_nearest(x, flagged, sources, (3, 3), free)
    assert y[4, 0] in (x[1, 0], x[3, 0], x[7, 0]) and y[5, 0] == x[2, 0]
    np.testing.assert_array_equal(y[:, 1], x[:, 1])
    np.testing.assert_array_equal(np.delete(y, [4, 5], 0), np.delete(x, [4, 5], 0))


def test_repair_says_why_it_was_skipped():
    from pbrfit.fit import _repair_skipped

    on = np.ones(5, np.float32)
    assert _repair_skipped("structured", (8, 8), on) is None
    assert _repair_skipped("structured", (1, 1), on) == "a uniform material"
    assert _repair_skipped("lm", (8, 8), on) == "needs the structured solver"
    assert _repair_skipped("structured", (8, 8), np.zeros(5)) == "no channel is fitted"
