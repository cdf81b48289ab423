"""The basin repair's host-side pieces (`pbrfit.fitting.stages.repair`); the whole repair is tested in test_fit."""

import numpy as np

from pbrfit.fitting.stages.repair import MISFIT_FLOOR, identifiable_texels, misfit_texels, outlier_texels, texel_misfit, well_seen_texels
from pbrfit.fitting.stages.repair import (NOISE_DEVIATIONS, evidence_variance, fill_from_nearest, improved_clusters,
                                         repair_region)
from pbrfit.fitting.uncertainty import residual_variance


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


def test_identifiable_texels_need_every_fitted_channel_constrained():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 8, 5))
    full = np.einsum("tpi,tpj->tij", a, a)  # rank 5: every channel constrained
    one_pixel = np.einsum("tpi,tpj->tij", a[:, :1], a[:, :1])  # rank 1: a pixel or two at a silhouette
    blocks = np.stack([full[0], one_pixel[1], full[2], full[3]])
    seen = np.array([True, True, True, False])
    fitted = np.ones(5, bool)
    np.testing.assert_array_equal(identifiable_texels(blocks, fitted, seen), [True, False, True, False])
    # a block blind to metallic alone: identifiable once metallic is held, not while it is fitted
    blind = full[2].copy()
    blind[3, :] = blind[:, 3] = 0.0
    blocks[2] = blind
    assert not identifiable_texels(blocks, fitted, seen)[2]
    held = fitted.copy()
    held[3] = False
    assert identifiable_texels(blocks, held, seen)[2]


def test_well_seen_texels_need_a_quarter_of_the_median_count():
    count = np.array([40, 40, 40, 12, 5, 0, 1])
    seen = np.array([True, True, True, True, True, False, True])
    # median over the seen texels (40 40 40 12 5 1): 26 -> at least 6.5 reads
    np.testing.assert_array_equal(well_seen_texels(count, seen), [True, True, True, True, False, False, False])
    assert not well_seen_texels(count, np.zeros(7, bool)).any()


def test_outlier_texels_flag_values_out_of_line_with_their_neighbours():
    # 6 x 6 roughness map at 0.5 with a texel at 0.9 and a texel 0.1 off (under the deviation)
    k, shape = 5, (6, 6)
    x = np.full((36, k), 0.5)
    x[1 * 6 + 1, 4] = 0.9
    x[4 * 6 + 1, 4] = 0.6
    trusted = np.ones(36, bool)
    fitted = np.array([True, True, True, False, True])
    expected = np.zeros(shape, bool)
    expected[1, 1] = True
    np.testing.assert_array_equal(outlier_texels(x, fitted, trusted, shape).reshape(shape), expected)
    # a held channel is never judged, nor an untrusted texel
    held = np.array([True, True, True, True, False])
    assert not outlier_texels(x, held, trusted, shape).any()
    untrusted = trusted.copy()
    untrusted[1 * 6 + 1] = False
    assert not outlier_texels(x, fitted, untrusted, shape).any()
    # untrusted texels are no reference: a map at 0.9 with four untrusted texels at 0.5 around
    # (1, 1) (half its neighbours) flags nothing
    lone = np.full((36, k), 0.9)
    lone[[2, 12, 13, 14], 4] = 0.5
    others = trusted.copy()
    others[[2, 12, 13, 14]] = False
    assert not outlier_texels(lone, fitted, others, shape).any()
    assert outlier_texels(lone, fitted, trusted, shape).reshape(shape)[1, 1]
    # rows past the map (padding) are ignored
    pad = lambda a, v: np.concatenate([a, np.full((4,) + a.shape[1:], v, a.dtype)])
    np.testing.assert_array_equal(outlier_texels(pad(x, 0.0), fitted, pad(trusted, False), shape), expected.reshape(-1))


def test_outlier_texels_peel_clusters_whose_texels_outnumber_their_good_neighbours():
    # a 3 x 3 cluster at 0.05 in a 0.5 map: at first only its corners are out of line with their
    # neighbours' median; without them, its edges are; then the centre has no unflagged neighbour
    fitted = np.array([False, False, False, False, True])
    judge = lambda x: outlier_texels(x.reshape(-1, 5), fitted, np.ones(256, bool), (16, 16)).reshape(16, 16)
    x = np.full((16, 16, 5), 0.5)
    x[2:5, 2:5, 4] = 0.05
    expected = np.zeros((16, 16), bool)
    expected[2:5, 2:5] = True
    np.testing.assert_array_equal(judge(x), expected)
    # in a map's corner a texel has three neighbours: under `OUTLIER_REFERENCES` of them, the median
    # is over the texels within two
    x = np.full((16, 16, 5), 0.5)
    x[:2, :2, 4] = 0.05
    expected = np.zeros((16, 16), bool)
    expected[:2, :2] = True
    np.testing.assert_array_equal(judge(x), expected)
    # where a first round flags over `OUTLIER_PEEL_SHARE` of the texels (a map of 2 x 2 patches),
    # it is the only one: peeling would eat the map
    rng = np.random.default_rng(0)
    x = np.zeros((8, 8, 5))
    x[..., 4] = np.kron(rng.uniform(0.08, 0.9, (4, 4)), np.ones((2, 2)))
    with_peel = outlier_texels(x.reshape(-1, 5), fitted, np.ones(64, bool), (8, 8))
    first = outlier_texels(x.reshape(-1, 5), fitted, np.ones(64, bool), (8, 8), share=1.0, peels=1)
    assert first.sum() > 0.1 * 64 and np.array_equal(with_peel, first)
    assert outlier_texels(x.reshape(-1, 5), fitted, np.ones(64, bool), (8, 8), share=1.0).sum() > first.sum()
    # a round after the first that would flag more than the share is not taken: the 3 x 3 cluster
    # (its 4 corners first, 4 of 256 texels, then its 4 edges) stops at its corners under 7 / 256
    x = np.full((16, 16, 5), 0.5)
    x[2:5, 2:5, 4] = 0.05
    corners = np.zeros((16, 16), bool)
    corners[2:5:2, 2:5:2] = True
    np.testing.assert_array_equal(outlier_texels(x.reshape(-1, 5), fitted, np.ones(256, bool), (16, 16),
                                                 share=7 / 256).reshape(16, 16), corners)
    # a straight edge between two patches is no outlier
    x = np.full((8, 8, 5), 0.5)
    x[:, 4:, 4] = 0.8
    assert not outlier_texels(x.reshape(-1, 5), fitted, np.ones(64, bool), (8, 8)).any()


def test_outlier_texels_do_not_compare_across_the_maps_edges():
    # stripes at 0.9 on the first and last columns of a 4-wide map, 0.5 between: across the
    # edges (a repeating wrap) the stripe's neighbours are mostly 0.9; within the map, 0.5
    x = np.full((5, 4, 5), 0.5)
    x[:, [0, 3], 4] = 0.9
    flagged = outlier_texels(x.reshape(-1, 5), np.ones(5, bool), np.ones(20, bool), (5, 4))
    expected = np.zeros((5, 4), bool)
    expected[:, [0, 3]] = True  # corners too: within two of them, 0.5 is the median
    np.testing.assert_array_equal(flagged.reshape(5, 4), expected)


def test_repair_region_grows_flags_by_one_ring_within_identifiable_texels():
    flagged = np.zeros(25, bool)
    flagged[12] = True  # the centre of a 5 x 5 map
    flagged[4] = True  # a corner: its ring wraps around the edges
    identifiable = np.ones(25, bool)
    identifiable[18] = False
    region = repair_region(flagged, identifiable, (5, 5)).reshape(5, 5)
    expected = np.zeros((5, 5), bool)
    expected[1:4, 1:4] = True
    expected[3, 3] = False  # not identifiable: held
    for i in (4, 0, 1):
        for j in (3, 4, 0):
            expected[i, j] = True
    np.testing.assert_array_equal(region, expected)


def test_improved_clusters_judges_each_cluster_by_its_own_pixels():
    # texels 0-5 in a row; pixels read neighbours (0,1), (1,2), (4,5), (5,5) and (3,3) with a
    # zero weight on texel 2; texel 3 is held, so {0, 1, 2} and {4, 5} are the clusters
    index = np.array([[0, 1, 0, 0], [1, 2, 1, 1], [4, 5, 4, 4], [5, 5, 5, 5], [3, 2, 3, 3]])
    weight = np.array([[0.5, 0.5, 0, 0], [0.5, 0.5, 0, 0], [0.5, 0.5, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    moving = np.array([True, True, True, False, True, True])
    before = np.ones((5, 3))
    after = before.copy()
    after[0] = 0.0  # cluster {0, 1, 2}: 6 -> 3 + 0 (pixel 1 unchanged)
    after[2] = 2.0  # cluster {4, 5}: 6 -> 12 + 3, although pixel 3 fits no worse
    after[4] = 0.0  # pixel 4 reads only the held texel 3: judged in no cluster
    better, clusters, improved = improved_clusters(moving, before, after, index, weight, 1)
    assert (clusters, improved) == (2, 1)
    np.testing.assert_array_equal(better, [True, True, True, False, False, False])
    # with a margin: cluster {0, 1, 2} fell by 3, kept under a margin of 2.9, not of 3
    assert improved_clusters(moving, before, after, index, weight, 1, margin=2.9)[2] == 1
    better, _, improved = improved_clusters(moving, before, after, index, weight, 1, margin=3.0)
    assert improved == 0 and not better.any()
    # with a spread: cluster {0, 1, 2} has 1 + 2 + 3 free channels (p = 6, √(2p) ≈ 3.46; the
    # held texel 3's 100 and cluster {4, 5}'s are not its), so it needs a fall of
    # 0.5 + 0.8 × 3.46 ≈ 3.27 > 3, or 0.5 + 0.7 × 3.46 ≈ 2.92 < 3
    dof = np.array([1, 2, 3, 100, 4, 5])
    assert improved_clusters(moving, before, after, index, weight, 1, 0.5, 0.8, dof)[2] == 0
    assert improved_clusters(moving, before, after, index, weight, 1, 0.5, 0.7, dof)[2] == 1
    # one free channel per texel by default: p = 3, 0.5 + 1.4 × 2.45 ≈ 3.93 > 3, 0.5 + 1.0 × 2.45 < 3
    assert improved_clusters(moving, before, after, index, weight, 1, 0.5, 1.4)[2] == 0
    assert improved_clusters(moving, before, after, index, weight, 1, 0.5, 1.0)[2] == 1
    # two samples per pixel: pixel 0's rows read (0, 1) and (4, 5), joining the clusters
    index2 = np.array([[0, 1, 0, 0], [4, 5, 4, 4]])
    weight2 = np.array([[0.5, 0.5, 0, 0], [0.5, 0.5, 0, 0]])
    moving2 = np.array([True, True, False, False, True, True])
    better, clusters, improved = improved_clusters(moving2, np.ones((1, 3)), np.zeros((1, 3)), index2, weight2, 2)
    assert (clusters, improved) == (1, 1) and np.array_equal(better, moving2)


def test_improved_clusters_bounds_what_a_refit_can_gain_under_noise():
    # one moving texel read by 100 pixels, each with 3 residuals of 1: m = 300 residuals, p = 1
    index = np.zeros((100, 4), np.int64)
    weight = np.zeros((100, 4))
    weight[:, 0] = 1.0
    moving = np.array([True, False])
    before = np.ones((100, 3))
    # under noise of variance 1 a re-fit reaches no less than 299 - 3 √598 ≈ 225.6, so the most
    # it can gain is about 74.4: possible under a margin of 74, not of 75
    least = 299 - NOISE_DEVIATIONS * np.sqrt(2 * 299)
    assert improved_clusters(moving, before, None, index, weight, 1, margin=300 - least - 0.1, noise=1.0)[2] == 1
    assert improved_clusters(moving, before, None, index, weight, 1, margin=300 - least + 0.1, noise=1.0)[2] == 0
    # noise of variance 2 leaves nothing to gain; no noise: the bound is 0, anything above the margin
    assert improved_clusters(moving, before, None, index, weight, 1, margin=1.0, noise=2.0)[2] == 0
    assert improved_clusters(moving, before, None, index, weight, 1, margin=299.0)[2] == 1


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


def test_evidence_variance_is_the_residual_variance_above_rounding():
    # under noise: the residual variance 2E / (n - p)
    assert evidence_variance(50.0, 10_000, 1_000, 0.2) == residual_variance(50.0, 10_000, 1_000) == 100.0 / 9_000
    # an exact fit (the noiseless peer scene's energy 1.4e-11 over 295k residuals): its rounding
    # is no evidence, so the variance is the misfit floor's
    assert residual_variance(1.4e-11, 294_912, 20_480) < 1e-15
    assert evidence_variance(1.4e-11, 294_912, 20_480, 0.2) == MISFIT_FLOOR * 0.2


def test_repair_says_why_it_was_skipped():
    from pbrfit.fitting.stages.repair import repair_skipped

    on = np.ones(5, np.float32)
    assert repair_skipped("structured", (8, 8), on) is None
    assert repair_skipped("structured", (1, 1), on) == "a uniform material"
    assert repair_skipped("lm", (8, 8), on) == "needs the structured solver"
    assert repair_skipped("structured", (8, 8), np.zeros(5)) == "no channel is fitted"
