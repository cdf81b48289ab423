"""Texels out of line after a solve: by their pixels' misfit, or by their values against their neighbours'.

The repair (`pbrfit.fitting.stages.repair`) restarts texels a solve left in a wrong basin; this room says which.
Two tests, each on the host, once per repair pass:

- by misfit (`misfit_texels`): the mean squared residual of the pixels that read a texel
  (`texel_misfit`) is more than `MISFIT_FACTOR` times the median over seen texels, and above
  `MISFIT_FLOOR` of the images' mean square (an exact fit's rounding flags nothing). Under noise
  alone a texel's mean is a chi-square mean of some hundred terms, within ±15% of the noise
  variance, so only a misfit the noise cannot explain is flagged;
- by value (`outlier_texels`): some fitted material channel lies more than `OUTLIER_DEVIATION`
  from the median of the texel's unflagged neighbours, peeled from a cluster's edge inwards.

Only texels the images determine are judged: their own pixels constrain every fitted channel
(`identifiable_texels`), and for the misfit test at least `WELL_SEEN_FRACTION` as many pixel rows
read them as read the median seen texel (`well_seen_texels`). The measurements behind each
threshold are in `pbrfit.fitting.stages.repair`'s docstring.

`texel_misfit` is the host-side twin of `pbrfit.fitting.initialisation._texel_scores` (divided by the
count): it runs once per pass on the solver's residuals, where a jitted scatter would add a
compile to every fit.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy import ndimage

from ..uncertainty import block_standard_errors

__all__ = ["MISFIT_FACTOR", "MISFIT_FLOOR", "WELL_SEEN_FRACTION", "OUTLIER_DEVIATION", "OUTLIER_REFERENCES",
           "OUTLIER_PEELS", "OUTLIER_PEEL_SHARE", "texel_misfit", "misfit_texels", "identifiable_texels",
           "well_seen_texels", "outlier_texels"]

#: A texel is flagged where its mean squared residual exceeds this many times the median.
MISFIT_FACTOR = 10.0
#: ... and this fraction of the mean squared target value (an exact fit's float32 rounding
#: leaves about 1e-14 of it).
MISFIT_FLOOR = 1e-8
#: A texel the repair may flag or move is read by at least this fraction of the pixel rows that
#: read the median seen texel.
WELL_SEEN_FRACTION = 0.25
#: The last pass flags an identifiable texel where a fitted material channel lies further than
#: this from the median of its unflagged identifiable neighbours (in the channel's units:
#: roughness, metallic and base colour all span [0, 1]; a normal map's slopes are not tested).
OUTLIER_DEVIATION = 0.15
#: With fewer unflagged neighbours than this among its eight, a texel is judged against the
#: texels within two of it (24 places; at a map's corner 3 neighbours, 8 within two).
OUTLIER_REFERENCES = 4
#: Most rounds of peeling a cluster of flagged texels from its edges inwards ...
OUTLIER_PEELS = 8
#: ... and a round is not taken where it would leave more than this share of the trusted texels
#: flagged: the median test assumes most texels sit in the right basin, and where they do not
#: (a map of 2 × 2 patches in a wrong start, 33 of 64 texels flagged at once) peeling eats the
#: map, leaving the fill no sources. Where a first round flags this many, it is the only one.
OUTLIER_PEEL_SHARE = 0.1


def texel_misfit(
    residuals: Float[np.ndarray, "P C"], index: Int[np.ndarray, "R 4"], weight: Float[np.ndarray, "R 4"],
    samples: int, num_texels: int,
) -> tuple[Float[np.ndarray, " T"], Int[np.ndarray, " T"]]:
    """Per texel, (the mean of ||r_p||² over the pixel rows that read it, how many rows read it).

    ``residuals`` are per pixel (rows past the index's pixels are ignored); ``index`` and
    ``weight`` per sample row, ``samples`` rows per pixel. A row reads a texel where its bilinear
    weight is positive; a texel no row reads has mean 0 and count 0."""
    r = np.asarray(residuals, np.float64)
    rows = index.shape[0]
    err = np.repeat(np.sum(r * r, axis=1), samples)[:rows]
    reads = np.asarray(weight) > 0
    idx = np.asarray(index)[reads]
    per_read = np.broadcast_to(err[:, None], reads.shape)[reads]
    total = np.bincount(idx, weights=per_read, minlength=num_texels)[:num_texels]
    count = np.bincount(idx, minlength=num_texels)[:num_texels]
    return np.where(count > 0, total / np.maximum(count, 1), 0.0), count


def misfit_texels(
    mean: Float[np.ndarray, " T"], count: Int[np.ndarray, " T"], seen: Bool[np.ndarray, " T"], scale: float,
    factor: float = MISFIT_FACTOR, floor: float = MISFIT_FLOOR,
) -> Bool[np.ndarray, " T"]:
    """Texels whose mean squared residual (`texel_misfit`) is above ``factor`` times the median of
    the seen texels' and above ``floor`` × ``scale`` (the images' mean squared value)."""
    use = np.asarray(seen, bool) & (count > 0)
    if not np.any(use):
        return np.zeros_like(use)
    median = float(np.median(mean[use]))
    return use & (mean > factor * median) & (mean > floor * scale)


def identifiable_texels(
    blocks: Float[np.ndarray, "T K K"], channels: Bool[np.ndarray, " K"], seen: Bool[np.ndarray, " T"],
) -> Bool[np.ndarray, " T"]:
    """Seen texels whose normal-matrix block D_t (`pbrfit.fitting.normal_matrix.normal_blocks`) constrains every
    fitted channel: the texels whose standard errors `pbrfit.fitting.uncertainty.block_standard_errors`
    finds finite (no eigenvalue of the block below its floor touches a fitted channel)."""
    channels = np.asarray(channels, bool)
    sigma = block_standard_errors(blocks, channels, seen, 1.0)
    return np.asarray(seen, bool) & np.all(np.isfinite(sigma[:, channels]), axis=1)


def well_seen_texels(
    count: Int[np.ndarray, " T"], seen: Bool[np.ndarray, " T"], fraction: float = WELL_SEEN_FRACTION,
) -> Bool[np.ndarray, " T"]:
    """Seen texels read by at least ``fraction`` times the median seen texel's count of pixel rows
    (`texel_misfit`'s count)."""
    seen = np.asarray(seen, bool) & (np.asarray(count) > 0)
    if not np.any(seen):
        return seen
    return seen & (count >= fraction * float(np.median(count[seen])))


#: Texels whose neighbourhoods `outlier_texels` gathers at once (bounds its memory: 24
#: neighbours × the judged channels × 8 bytes × this).
_CHUNK = 1 << 15


def _neighbour_count(ok: Bool[np.ndarray, "H W"], n: int) -> Int[np.ndarray, "H W"]:
    """Per texel, how many ``ok`` texels lie within ``n`` of it (not itself, not across the map's
    edges)."""
    kernel = np.ones((2 * n + 1, 2 * n + 1), np.int64)
    kernel[n, n] = 0
    return ndimage.convolve(ok.astype(np.int64), kernel, mode="constant", cval=0)


def _neighbour_median(
    v: Float[np.ndarray, "H W K"], ok: Bool[np.ndarray, "H W"], ys: Int[np.ndarray, " N"],
    xs: Int[np.ndarray, " N"], n: int,
) -> tuple[Float[np.ndarray, "N K"], Bool[np.ndarray, " N"]]:
    """At texels (ys, xs), the median of the ``ok`` texels within ``n`` of each (not itself, not
    across the map's edges; the mean of the middle two for an even count), and whether there are
    any. Gathered `_CHUNK` texels at a time."""
    h, w, k = v.shape
    dy, dx = np.array([(a, b) for a in range(-n, n + 1) for b in range(-n, n + 1) if a or b]).T
    median = np.zeros((len(ys), k))
    count = np.zeros(len(ys), np.int64)
    for s in range(0, len(ys), _CHUNK):
        y, x = ys[s:s + _CHUNK, None] + dy, xs[s:s + _CHUNK, None] + dx
        inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
        y, x = np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)
        valid = inside & ok[y, x]
        vals = np.sort(np.where(valid[..., None], v[y, x], np.inf), axis=1)  # the valid ones first
        c = valid.sum(axis=1)
        middle = lambda i: np.take_along_axis(vals, np.broadcast_to(i[:, None, None], (len(c), 1, k)), axis=1)[:, 0]
        mid = 0.5 * (middle(np.maximum(c - 1, 0) // 2) + middle(c // 2))  # c // 2 < c <= len(dy)
        median[s:s + _CHUNK] = np.where(c[:, None] > 0, mid, 0.0)
        count[s:s + _CHUNK] = c
    return median, count > 0


def outlier_texels(
    x: Float[np.ndarray, "T K"], channels: Bool[np.ndarray, " K"], trusted: Bool[np.ndarray, " T"],
    shape: tuple[int, int], deviation: float = OUTLIER_DEVIATION, references: int = OUTLIER_REFERENCES,
    peels: int = OUTLIER_PEELS, share: float = OUTLIER_PEEL_SHARE,
) -> Bool[np.ndarray, " T"]:
    """Trusted texels where some fitted channel c differs by more than ``deviation`` from the
    median of the unflagged trusted texels among its eight neighbours on the (H, W) grid (not
    across the map's edges), or within two of it where fewer than ``references`` of those are
    left. Peeled in rounds (at most ``peels``; after the first, a round is taken only where no
    more than ``share`` of the trusted texels end up flagged): each judges the texels not yet
    flagged against the texels not yet flagged, and also flags a texel whose trusted neighbours
    all are. Peeling reaches the centre of clusters up to three texels wide whose values lie more
    than twice ``deviation`` off (at the edge of a 3 × 3 cluster, with its corners flagged, the
    median is that of three good and three bad values); wider clusters, or closer ones, are
    flagged at their corners, and the repair's region (one ring around the flags) re-solves more
    of them."""
    h, w = shape
    t = h * w
    ok = np.asarray(trusted[:t], bool).reshape(h, w)
    judged = np.asarray(channels, bool)
    flagged = np.zeros((h, w), bool)
    if not np.any(judged):
        return flagged.reshape(-1)
    v = np.asarray(x[:t], np.float64).reshape(h, w, -1)[..., judged]
    count = _neighbour_count(ok, 1)
    # a texel's judgement depends only on the texels within two of it: after the first round only
    # those near the texels the last round flagged can change
    candidates = ok
    for _ in range(peels):
        reference = ok & ~flagged
        ys, xs = np.nonzero(reference & candidates)
        median, have = _neighbour_median(v, reference, ys, xs, 1)
        few = _neighbour_count(reference, 1)[ys, xs] < references
        if np.any(few):
            median[few], have[few] = _neighbour_median(v, reference, ys[few], xs[few], 2)
        out = have & np.any(np.abs(v[ys, xs] - median) > deviation, axis=-1)
        enclosed = (count > 0) & (_neighbour_count(ok & flagged, 1) == count)
        new = np.zeros((h, w), bool)
        new[ys, xs] = out | enclosed[ys, xs]
        if not np.any(new) or (np.any(flagged) and np.sum(flagged | new) > share * np.sum(ok)):
            break
        flagged |= new
        candidates = ndimage.maximum_filter(new, size=5, mode="constant", cval=False)
    return flagged.reshape(-1)
