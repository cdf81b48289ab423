"""Standard errors from the normal matrix's blocks (`pbrfit.fitting.uncertainty`), on random normal
matrices of pixels that read four neighbouring texels, built densely here."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pbrfit.fitting import uncertainty
from pbrfit.fitting.normal_matrix import NEIGHBOUR_OFFSETS
from pbrfit.fitting.uncertainty import (block_standard_errors, sandwich_ratios, window_precisions, window_radii,
                                        window_standard_errors)


def _normal_matrix(shape, k, pixels, seed, wrap=True):
    """(JᵀJ dense (T K, T K), its diagonal blocks (T, K, K), its neighbour blocks (T, 4, K, K) laid
    out as `pbrfit.fitting.normal_matrix.neighbour_blocks` gives them) for random pixels, each reading the four
    texels around a random point with bilinear weights, each tap through the pixel's 3 × K Jacobian
    plus some of its own (as a pixel's samples have: the blocks between texels are then not
    symmetric). Without
    ``wrap`` no pixel reads across the map's edge."""
    h, w = shape
    t = h * w
    rng = np.random.default_rng(seed)
    jac = np.zeros((3 * pixels, t * k))
    for p in range(pixels):
        i, j = (rng.integers(h), rng.integers(w)) if wrap else (rng.integers(h - 1), rng.integers(w - 1))
        fy, fx = rng.random(2)
        jp = rng.normal(size=(3, k))
        taps = ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx), (1, 0, fy * (1 - fx)), (1, 1, fy * fx))
        for di, dj, weight in taps:
            u = ((i + di) % h) * w + (j + dj) % w
            jac[3 * p:3 * p + 3, u * k:(u + 1) * k] += weight * (jp + 0.3 * rng.normal(size=(3, k)))
    a = jac.T @ jac

    def block(s, u):
        return a[s * k:(s + 1) * k, u * k:(u + 1) * k]

    diag = np.stack([block(s, s) for s in range(t)])
    assert np.abs(block(0, 1) - block(0, 1).T).max() > 1e-3 * np.abs(block(0, 1)).max()
    coupling = np.stack([[block(s, ((s // w + di) % h) * w + (s % w + dj) % w) for di, dj in NEIGHBOUR_OFFSETS]
                         for s in range(t)])
    return a, diag, coupling


def test_window_radii_keep_the_window_inside_the_map():
    assert window_radii((64, 64), 1) == (1, 1)
    assert window_radii((64, 32), 3) == (3, 3)
    assert window_radii((4, 5), 2) == (1, 1)  # 2 r + 2 <= H: no texel of the window is another's wrapped neighbour
    assert window_radii((3, 3), 1) == (0, 0)
    assert window_radii((1, 8), 1) == (0, 1)
    assert window_radii((1, 1), 2) == (0, 0)


def test_radius_zero_is_the_per_texel_blocks():
    _, diag, coupling = _normal_matrix((5, 6), 3, 200, seed=0)
    channels, seen = np.ones(3, bool), np.ones(30, bool)
    np.testing.assert_array_equal(window_standard_errors(diag, coupling, (5, 6), channels, seen, 2.0, radius=0),
                                  block_standard_errors(diag, channels, seen, 2.0))
    # a map too small for any window falls back to the blocks as well
    _, diag3, coupling3 = _normal_matrix((3, 3), 3, 60, seed=1)
    np.testing.assert_array_equal(window_standard_errors(diag3, coupling3, (3, 3), channels, np.ones(9, bool), 1.0),
                                  block_standard_errors(diag3, channels, np.ones(9, bool), 1.0))


@pytest.mark.parametrize("radius", [1, 2])
@pytest.mark.parametrize("chunk_bytes, threads", [(None, 1), (29160, 1), (29160, 3)])
def test_window_is_the_inverse_of_its_part_of_the_matrix(radius, chunk_bytes, threads, monkeypatch):
    """σ² of a texel is σ̂² times the diagonal of the inverse of JᵀJ restricted to the texel's
    window (wrapping around the map), at the texel's channels: inside the map and on its edges;
    the same where the windows are assembled a few texels at a time (29160 bytes: 5 texels a
    chunk at radius 1, the last chunk 2; one at radius 2), and where threads share the chunks
    (and the blocks' eigenpairs)."""
    if chunk_bytes is not None:
        monkeypatch.setattr(uncertainty, "_WINDOW_CHUNK_BYTES", chunk_bytes)
    monkeypatch.setattr(uncertainty, "_threads", lambda: threads)
    shape, k, sigma2 = (6, 7), 3, 0.5
    a, diag, coupling = _normal_matrix(shape, k, 400, seed=2)
    got = window_standard_errors(diag, coupling, shape, np.ones(k, bool), np.ones(42, bool), sigma2, radius)
    h, w = shape
    for s in (0, 6, 17, 24, 41):
        i, j = divmod(s, w)
        texels = [((i + di) % h) * w + (j + dj) % w for di in range(-radius, radius + 1)
                  for dj in range(-radius, radius + 1)]
        cols = np.concatenate([np.arange(u * k, (u + 1) * k) for u in texels])
        inverse = np.linalg.inv(a[np.ix_(cols, cols)])
        c = texels.index(s)
        want = np.sqrt(sigma2 * np.diag(inverse)[c * k:(c + 1) * k])
        np.testing.assert_allclose(got[s], want, rtol=1e-6)


def test_chunks_in_threads_cover_every_row_once_and_an_error_cancels_the_rest(monkeypatch):
    """`_in_chunks` hands each row to one chunk, on several threads; a chunk's error is raised,
    and the chunks not begun are not run."""
    monkeypatch.setattr(uncertainty, "_threads", lambda: 3)
    seen = np.zeros(103, int)

    def count(lo, hi):
        seen[lo:hi] += 1

    uncertainty._in_chunks(count, 103, 10)
    np.testing.assert_array_equal(seen, 1)
    begun = []

    def fail(lo, hi):
        begun.append(lo)
        if lo == 3:
            raise ValueError("chunk 3")
        time.sleep(0.01)

    with pytest.raises(ValueError, match="chunk 3"):
        uncertainty._in_chunks(fail, 200, 1)
    time.sleep(0.1)  # (chunks under way when it raised end)
    assert len(begun) < 50


def test_errors_grow_with_the_window_towards_the_marginal():
    """Per-texel blocks <= radius 1 <= radius 2 <= the marginal σ of the whole matrix, and the
    wider window is the closer."""
    shape, k = (8, 8), 3
    a, diag, coupling = _normal_matrix(shape, k, 300, seed=3, wrap=False)
    channels, seen = np.ones(k, bool), np.ones(64, bool)
    marginal = np.sqrt(np.diag(np.linalg.inv(a))).reshape(64, k)
    sigmas = [window_standard_errors(diag, coupling, shape, channels, seen, 1.0, r) for r in (0, 1, 2)]
    for lo, hi in zip(sigmas, sigmas[1:] + [marginal]):
        assert np.all(lo <= hi * (1 + 1e-9))
    ratios = [np.median(s / marginal) for s in sigmas]
    assert ratios[0] < ratios[1] < ratios[2] <= 1.0 and ratios[0] < 0.9 and ratios[2] > 0.97, ratios


def test_fixed_unseen_and_unconstrained_channels():
    """A fixed channel has σ 0, an unseen texel +inf; a channel no pixel constrains at one texel
    is +inf there and leaves its neighbours' errors finite."""
    shape, k = (6, 6), 3
    a, diag, coupling = _normal_matrix(shape, k, 300, seed=4)
    unseen, blind = 14, 21  # texel 21's channel 2 is read by no pixel
    for t, cs in ((unseen, slice(None)), (blind, slice(2, 3))):
        diag[t][cs, :] = 0.0
        diag[t][:, cs] = 0.0
    for t in range(36):
        for q, (di, dj) in enumerate(NEIGHBOUR_OFFSETS):
            u = ((t // 6 + di) % 6) * 6 + (t % 6 + dj) % 6
            if t == unseen:
                coupling[t, q] = 0.0
            if u == unseen:
                coupling[t, q] = 0.0
            if t == blind:
                coupling[t, q, 2, :] = 0.0
            if u == blind:
                coupling[t, q, :, 2] = 0.0
    seen = np.ones(36, bool)
    seen[unseen] = False
    channels = np.array([True, False, True])
    got = window_standard_errors(diag, coupling, shape, channels, seen, 1.0, radius=1)
    assert np.all(got[:, 1] == 0.0)
    assert np.all(np.isinf(got[unseen, [0, 2]]))
    assert np.isinf(got[blind, 2]) and np.isfinite(got[blind, 0])
    others = np.setdiff1d(np.arange(36), [unseen, blind])
    assert np.all(np.isfinite(got[others][:, [0, 2]]))
    own = block_standard_errors(diag, channels, seen, 1.0)
    assert np.all(got[others][:, [0, 2]] >= own[others][:, [0, 2]])
    # next to the unseen texel: the window's matrix without it and without the fixed channel
    zeroed = a.copy()
    for t, cs in ((unseen, [0, 1, 2]), (blind, [2])):
        for c in cs:
            zeroed[3 * t + c, :] = zeroed[:, 3 * t + c] = 0.0
    s = 15
    texels = [((s // 6 + di) % 6) * 6 + (s % 6 + dj) % 6 for di in (-1, 0, 1) for dj in (-1, 0, 1)]
    cols = [3 * u + c for u in texels if u != unseen for c in (0, 2) if not (u == blind and c == 2)]
    inverse = np.linalg.inv(zeroed[np.ix_(cols, cols)])
    np.testing.assert_allclose(got[s, [0, 2]], np.sqrt(np.diag(inverse)[[cols.index(3 * s), cols.index(3 * s + 2)]]),
                               rtol=1e-6)
    # the precisions themselves: none for the unseen texel or the blind channel, finite elsewhere
    p = window_precisions(diag, coupling, shape, channels, seen, 1)
    assert np.all(np.isfinite(p)) and np.all(p[unseen] == 0.0)
    assert np.all(p[blind, 2, :] == 0.0) and np.all(p[blind, :, 2] == 0.0) and p[blind, 0, 0] > 0.0


def test_channels_on_a_bound_are_held_for_the_others():
    """A channel pinned on a bound (where the projected solver holds it) is held for the other
    channels' errors, at its own texel and in its neighbours' windows; its own error stays the
    free one."""
    shape, k = (6, 6), 3
    a, diag, coupling = _normal_matrix(shape, k, 300, seed=5)
    channels, seen = np.ones(k, bool), np.ones(36, bool)
    pinned = np.zeros((36, k), bool)
    pinned[14, 0] = pinned[15, 2] = True
    free = window_standard_errors(diag, coupling, shape, channels, seen, 1.0, 1)
    got = window_standard_errors(diag, coupling, shape, channels, seen, 1.0, 1, pinned)
    np.testing.assert_array_equal(got[pinned], free[pinned])
    for s in (14, 15, 21):  # texel 21 has both pinned texels in its window
        texels = [((s // 6 + di) % 6) * 6 + (s % 6 + dj) % 6 for di in (-1, 0, 1) for dj in (-1, 0, 1)]
        cols = [3 * u + c for u in texels for c in range(k) if not pinned[u, c]]
        inverse = np.linalg.inv(a[np.ix_(cols, cols)])
        mine = [c for c in range(k) if not pinned[s, c]]
        want = np.sqrt(np.diag(inverse)[[cols.index(3 * s + c) for c in mine]])
        np.testing.assert_allclose(got[s, mine], want, rtol=1e-6)
        assert np.all(got[s, mine] <= free[s, mine] * (1 + 1e-9))
    far = np.ones(36, bool)
    far[[t for s in (14, 15) for t in [((s // 6 + di) % 6) * 6 + (s % 6 + dj) % 6 for di in (-1, 0, 1)
                                       for dj in (-1, 0, 1)]]] = False
    np.testing.assert_array_equal(got[far], free[far])  # windows without a pinned channel: unchanged



def test_a_cache_recomputes_the_windows_that_hold_a_change_and_keeps_the_others(monkeypatch):
    """With a `WindowCache`, a second call whose blocks, couplings, channels and pinned channels
    changed at a few texels gives the same errors as a call without one, and computes the
    windows of the texels within a window's reach of the changes alone."""
    shape, k = (9, 10), 3
    t = 90
    _, diag, coupling = _normal_matrix(shape, k, 900, seed=7)
    channels, seen = np.ones((t, k), bool), np.ones(t, bool)
    seen[44] = False
    pinned = np.zeros((t, k), bool)
    pinned[[3, 60], 1] = True
    computed = []
    real = uncertainty.window_precisions

    def counted(*args, **kwargs):
        texels = args[6] if len(args) > 6 else kwargs.get("texels")
        computed.append(t if texels is None else len(texels))
        return real(*args, **kwargs)

    monkeypatch.setattr(uncertainty, "window_precisions", counted)
    factored = []  # the rows whose eigen-decompositions are computed
    real_factors = uncertainty._variance_factors
    monkeypatch.setattr(uncertainty, "_variance_factors", lambda m, *a: factored.append(len(m)) or real_factors(m, *a))
    cache = uncertainty.WindowCache()
    first = window_standard_errors(diag, coupling, shape, channels, seen, 0.7, 1, pinned, cache)
    np.testing.assert_array_equal(first, window_standard_errors(diag, coupling, shape, channels, seen, 0.7, 1, pinned))
    diag2, coupling2, channels2, pinned2 = diag.copy(), coupling.copy(), channels.copy(), pinned.copy()
    diag2[12] *= 1.5  # a block at (1, 2), a coupling at (8, 0) (its window wraps), a channel at (4, 7)
    coupling2[80, 2] += 0.1
    channels2[47, 2] = False
    pinned2[60, 1] = False  # texel (6, 0) leaves its bound
    computed.clear()
    got = window_standard_errors(diag2, coupling2, shape, channels2, seen, 1.3, 1, pinned2, cache)
    # the 3 × 3 windows around the block, the coupling and the channel (26 texels: two overlap at
    # (0, 1)), every channel free; with the pinned ones held, those around (6, 0) as well (3 more overlap)
    assert computed == [26, 32], computed
    np.testing.assert_array_equal(got, window_standard_errors(diag2, coupling2, shape, channels2, seen, 1.3, 1,
                                                              pinned2))
    # nothing changed: nothing computed, the errors scaled by σ̂² alone
    computed.clear()
    factored.clear()
    again = window_standard_errors(diag2, coupling2, shape, channels2, seen, 2.6, 1, pinned2, cache)
    assert computed == [] and factored == [], (computed, factored)
    np.testing.assert_allclose(again, got * np.sqrt(2.0), rtol=1e-6)
    # a texel seen now: the windows around it
    seen[44] = True
    computed.clear()
    got = window_standard_errors(diag2, coupling2, shape, channels2, seen, 1.3, 1, pinned2, cache)
    assert computed == [9, 9], computed
    np.testing.assert_array_equal(got, window_standard_errors(diag2, coupling2, shape, channels2, seen, 1.3, 1,
                                                              pinned2))

def test_non_finite_values_outside_the_fit_do_not_reach_the_others():
    """A fixed channel's derivatives and an unseen texel's blocks take no part: NaN or inf there
    leaves every other texel's precision and error as with zeros."""
    shape, k = (6, 6), 3
    _, diag, coupling = _normal_matrix(shape, k, 300, seed=5)
    channels = np.array([True, False, True])
    seen = np.ones(36, bool)
    seen[20] = False
    clean = window_precisions(diag, coupling, shape, channels, seen, 1)
    diag, coupling = diag.copy(), coupling.copy()
    diag[:, 1, :] = diag[:, :, 1] = np.nan  # the fixed channel
    coupling[:, :, 1, :] = coupling[:, :, :, 1] = np.nan
    diag[20] = np.inf  # the unseen texel, and its couplings both ways
    coupling[20] = np.inf
    for q, (di, dj) in enumerate(NEIGHBOUR_OFFSETS):
        coupling[((20 // 6 - di) % 6) * 6 + (20 % 6 - dj) % 6, q] = -np.inf
    np.testing.assert_array_equal(window_precisions(diag, coupling, shape, channels, seen, 1), clean)
    assert np.all(window_precisions(diag, coupling, shape, np.zeros(k, bool), seen, 1) == 0.0)  # none fitted
    sigma = window_standard_errors(diag, coupling, shape, channels, seen, 1.0, 1)
    assert np.all(sigma[:, 1] == 0.0) and np.all(np.isinf(sigma[20, [0, 2]]))
    assert np.all(np.isfinite(np.delete(sigma, 20, axis=0)))


def _pixel_rows(k, pixels, seed):
    """(P, 3, K) random per-pixel Jacobians of one texel, and their block D = Σ J_pᵀJ_p."""
    jac = np.random.default_rng(seed).normal(size=(pixels, 3, k))
    return jac, np.einsum("pci,pcj->ij", jac, jac)


def _meat(jac, r):
    g = np.einsum("pck,pc->pk", jac, r)
    return np.einsum("pi,pj->ij", g, g)


def test_sandwich_ratio_reads_the_residuals_variance_against_the_noise_model():
    """ρ = [D⁻¹ M D⁻¹]_cc / (σ̂² [D⁻¹]_cc): exactly s where M = s σ̂² D; about 1 for residuals of
    the noise model's variance; above 1 in the channel whose informative pixels carry more."""
    k, sigma2 = 3, 0.04
    jac, d = _pixel_rows(k, 4000, seed=0)
    blocks = np.stack([d, d, d])
    seen, channels = np.ones(3, bool), np.ones(k, bool)
    exact = sandwich_ratios(blocks, np.stack([sigma2 * d, 2.5 * sigma2 * d, sigma2 * d / 1.25]), channels, seen,
                            sigma2, dof_scale=1.25)
    np.testing.assert_allclose(exact, [[1.25] * k, [3.125] * k, [1.0] * k], rtol=1e-10)
    rng = np.random.default_rng(1)
    noise = rng.normal(0, np.sqrt(sigma2), size=(4000, 3))
    # more residual where the pixel's derivative in channel 0 is large: light the model misses there
    loud = noise * (1 + 3 * (np.abs(jac[:, :, 0]) > 1.5))
    got = sandwich_ratios(blocks, np.stack([_meat(jac, noise), _meat(jac, loud), _meat(jac, noise)]), channels, seen,
                          sigma2)
    np.testing.assert_allclose(got[0], 1.0, atol=0.1)
    assert got[1, 0] > 3 and got[1, 0] > 1.5 * got[1, 1:].max()


def test_sandwich_ratio_is_one_where_sigma_says_nothing_and_holds_pinned_channels():
    """Unseen texels, fixed channels and channels on a degenerate direction get 1; a pinned
    channel is held for the others (their ratio that of the block without it), its own is the
    ratio with all free."""
    k, sigma2 = 3, 1.0
    jac, d = _pixel_rows(k, 500, seed=2)
    meat = _meat(jac, np.random.default_rng(3).normal(0, 2.0, size=(500, 3)))
    blind = d.copy()
    blind[2, :] = blind[:, 2] = 0.0
    blind_meat = meat.copy()
    blind_meat[2, :] = blind_meat[:, 2] = 0.0
    blocks, meats = np.stack([d, d, blind]), np.stack([meat, meat, blind_meat])
    seen = np.array([True, False, True])
    channels = np.array([True, False, True])
    got = sandwich_ratios(blocks, meats, channels, seen, sigma2)
    assert np.all(got[:, 1] == 1.0) and np.all(got[1] == 1.0) and got[2, 2] == 1.0
    assert got[0, 0] > 2 and got[2, 0] > 2  # residuals of std 2 against σ̂ 1
    pinned = np.zeros((3, k), bool)
    pinned[0, 0] = True
    held = sandwich_ratios(blocks, meats, channels, seen, sigma2, pinned=pinned)
    assert held[0, 0] == got[0, 0]
    d_c, m_c = d[2, 2], meat[2, 2]  # channel 2 alone: (m / d²) / (σ̂² / d)
    np.testing.assert_allclose(held[0, 2], m_c / d_c / sigma2, rtol=1e-10)
    np.testing.assert_array_equal(held[1:], got[1:])
