"""Repair of texels a solve left in a wrong basin, found by their residuals.

A solve ends in a local minimum where a few neighbouring texels settle into values that make up
for each other: at the edge of two patches of different roughness, one texel too rough and the
next too smooth reproduce the pixels that blend them about as well as the truth does, and every
single-texel move towards the truth raises the objective (measured on the peer scene's seed 3:
all 65 such texels; moved together, the objective falls from 0.27 to 0). Neither the coordinate
search, which moves one texel at a time, nor the solver leaves such a cluster.

The repair finds the cluster by its misfit and starts it again from outside:

1. `misfit_texels`: a texel is flagged where the mean squared residual of the pixels that read it
   is more than `MISFIT_FACTOR` times the median over seen texels (and above `MISFIT_FLOOR` of
   the images' mean square, so that the rounding error of an exact fit flags nothing). Under
   noise alone a texel's mean is a chi-square mean of some hundred terms, within ±15% of the
   noise variance, so only a misfit the noise cannot explain is flagged.
   Only texels the images determine well are flagged: their own pixels constrain every fitted
   channel (`identifiable_texels`) and at least `WELL_SEEN_FRACTION` as many pixel rows read them
   as read the median seen texel (`well_seen_texels`). A few pixels at a silhouette or a pole
   leave their texels' values free, jointly if not one by one, so a lower objective there says
   nothing about the truth: on the noiseless spheres-grid preset, restarting such texels fitted
   the images 1,750 times better and doubled every map's RMSE; with identifiable texels alone,
   75 texels read by a median of 3 pixels (the median seen texel: 28) still went from errors of
   0.02-0.04 to 0.1-0.2.
2. `fill_from_nearest`: each flagged texel takes the fitted values of the nearest well-determined
   texel that is not flagged (the basin of the patch around it).
3. The fit's coordinate search (`pbrfit.fitting.initialisation.coordinate_search`, `REPAIR_ROUNDS`
   sweeps) and `REPAIR_STEPS` solver steps follow (`run_repair`), moving only the flagged
   texels and their well-determined neighbours (`repair_region`: the eight around each, which a
   pixel's bilinear taps read together with it); every other texel keeps its value.
4. `improved_clusters`: the moved texels fall into clusters that share no pixel, so each
   cluster's pixels judge it alone. A cluster is kept where the squared residuals of its pixels
   fell, and the pass is kept where the whole objective then falls; further passes run, up to
   `REPAIR_PASSES`, while a pass lowers the objective by more than `REPAIR_PROGRESS` of it.
5. `outlier_texels`: one last pass flags, instead of the misfit, the identifiable texels (well
   seen or not) whose value of some fitted material channel (not a normal map's slopes) lies
   more than `OUTLIER_DEVIATION` from the median of its identifiable neighbours, and runs steps
   2 to 4 on them. Under noise a wrong basin's misfit can hide in the noise, and a cluster the
   misfit passes could not move need not show one either; both leave texels out of line with
   the patch around them. A cluster of such texels outnumbers the good neighbours of its inner
   texels, so the test peels it: each round judges the texels left against the unflagged ones
   only, and a texel whose neighbours are all flagged is flagged with them (a round after the
   first only while no more than `OUTLIER_PEEL_SHARE` of the identifiable texels end up
   flagged; peeling reaches the centre of clusters up to three texels wide whose values lie over
   0.3 off, and flags wider ones at their corners); where fewer than `OUTLIER_REFERENCES`
   unflagged neighbours remain (a map's corner), the median is over the texels within two. No
   standard error enters the test: a texel in a wrong basin has its σ from that basin. A texel
   that is out of line in the truth (a patch's corner, a scratch) comes back to its value in the
   re-solve and its cluster is put back: the test proposes, the pixels decide. Under noise they
   decide only with evidence: a cluster is kept where its pixels' Σ ||r||² fell by more than
   (`OUTLIER_EVIDENCE` + `OUTLIER_SPREAD` √(2p)) σ̂², σ̂² the residual variance (no less than
   the misfit floor: an exact fit's rounding is no evidence) and p the cluster's free channels
   (√(2p) σ̂² is the spread of a χ² with p degrees of freedom: a large cluster re-solved into
   another fit of the same noise moves its Σ ||r||² by about that much either way).
   Measured on ten renditions of the peer scene (`experiments/seeds.md`): noiseless, seeds 7 and
   9, which the misfit passes leave at roughness RMSE 0.011 and 0.009, become exact. With noise
   of 1% of each pixel's value, seed 5 ended at 0.035 when the test judged well-seen texels by
   3σ against their eight neighbours: a 3 × 3 cluster in the map's corner sat at the floor of
   roughness under a truth of 0.77, read by 12 to 18 pixels (about 50 for the median texel),
   with σ up to 0.24 in that basin, and only its rim was flagged. Now all of it is, and seed 5
   ends at 0.025 (0.024 from the true maps), seed 9 at 0.014 (0.028). On the flash scene with
   1% noise, without the √(2p) term, a cluster of 1,743 texels that fit better by about 43 σ̂²
   took metallic from 0.036 to 0.049 RMSE; its threshold is 274 σ̂², and it is put back. It
   costs a search and `REPAIR_STEPS` steps per pass. On a 2-core CPU the repair's time besides
   its steps (report.json's ``times.repair``, mostly its searches) was 2.7 s in `pbrfit demo`'s
   fit and 6.5 s on the flash scene with 1% noise (2 × 2 samples per pixel), each search over
   the moved texels' pixels alone where that costs less (`search_problem`): 7.3 and 13.4 s over
   every pixel. Each search also runs over the texels its pixels read alone (`take_texels`),
   so its time follows the region's size, not the map's: on the noiseless peer layout at 512²
   (16 views) the three searches took 34 s over a quarter, a quarter and a sixteenth of the
   pixels, against 149 s with every texel (two of them then searched every pixel); at 1024² the
   repair's time besides its steps fell from 685 to 187 s (experiments/speed.md). It runs only
   where some cluster could clear its threshold: where its pixels' Σ ||r||² lies that far above
   the least a re-fit reaches under the fit's residual variance (`NOISE_DEVIATIONS`); on the
   noiseless flash scene, whose 16-bit images are fitted to their rounding, none can, and the
   pass is skipped.

Which texels are out of line after a solve, by their pixels' misfit or by their values against
their neighbours':
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
threshold are above.

`texel_misfit` is the host-side twin of `pbrfit.fitting.initialisation._texel_scores` (divided by the
count): it runs once per pass on the solver's residuals, where a jitted scatter would add a
compile to every fit.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import numpy as np
from jaxtyping import Bool, Float, Int
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from ..initialisation import coordinate_search
from ..parameters import CHANNELS
from ..runner import jitted_normal_blocks, pixel_rows_from, problem_energy, problem_key, search_inputs, timed
from ..sharding import (halving_sizes, mesh_size, moving_pixels, set_texel_rows, take_pixels, take_texels,
                        texel_program, texel_rows)
from ..solvers.names import DEFAULT_SOLVER, is_structured
from ..objective import Problem
from ...transfer import to_device
from ..uncertainty import block_standard_errors, residual_variance

__all__ = ["REPAIR_ROUNDS", "REPAIR_STEPS", "REPAIR_PASSES", "REPAIR_PROGRESS", "OUTLIER_EVIDENCE", "OUTLIER_SPREAD", "NOISE_DEVIATIONS",
           "repair_region", "fill_from_nearest", "improved_clusters", "evidence_variance", "repair_skipped",
           "run_repair", "search_problem", "SEARCH_COMPILE_COST", "SEARCH_COMPILE_PIXELS",
           "MISFIT_FACTOR", "MISFIT_FLOOR", "WELL_SEEN_FRACTION", "OUTLIER_DEVIATION", "OUTLIER_REFERENCES",
           "OUTLIER_PEELS", "OUTLIER_PEEL_SHARE", "texel_misfit", "misfit_texels", "identifiable_texels",
           "well_seen_texels", "outlier_texels"]

# --- which texels are out of line ----------------------------------------------------------

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


# --- the repair ------------------------------------------------------------------------------


#: Sweeps of the coordinate search in a repair (one sweep leaves texels whose neighbours the
#: sweep moved after them: on the peer scene's seed 3, roughness RMSE 0.013 after one, exact
#: after two).
REPAIR_ROUNDS = 2
#: A compile of a search's program, counted in searches of every pixel (`search_problem`): less
#: than a cold compile takes (on a 2-core CPU 3.3 s against a 2.0 s search on the demo, 1.9 s
#: against 0.7 s on the peer scene), as a program compiled once serves the passes after it and,
#: from the persistent cache, later fits. So a search over 1/8 of the pixels or fewer pays for
#: its compile, over 1/4 not. `pbrfit demo`'s fit, whose three misfit passes search 1/16 of the
#: pixels, took 28.2 s with empty caches and 16.3 s warm, against 30.3 and 20.0 s searching all.
SEARCH_COMPILE_COST = 0.75
#: ... but no more than a search over this many pixels: a compile takes about as long whatever
#: the pixels, a search in proportion to them (on a 2-core CPU, 2 to 3 s against 20 to 27 µs a
#: pixel for the repair's two sweeps on the peer layout at 256² and 512²).
SEARCH_COMPILE_PIXELS = 150_000
#: Solver steps after a repair's search.
REPAIR_STEPS = 20
#: Most misfit passes per fit (the outlier pass comes after them).
REPAIR_PASSES = 3
#: A further pass runs only where the one before lowered the objective by more than this
#: fraction of it (on spheres-grid at 128 x 128, after a first pass that took 60%, a second and
#: a third gained 2e-5 and 2e-6 of the objective, each for a search and 20 steps).
REPAIR_PROGRESS = 0.01
#: A cluster the outlier pass moves is kept only where its pixels' Σ ||r||² fell by more than
#: this many residual variances σ̂² (a likelihood ratio over e^5 for the new basin): more steps on a
#: settled fit lower it by less, and such moves shuffle the maps within their noise ...
OUTLIER_EVIDENCE = 10.0
#: ... plus this many times √(2p) σ̂², p the cluster's free channels: the spread of Σ ||r||² between
#: two fits of the same noise (χ² with p degrees of freedom).
OUTLIER_SPREAD = 2.0
#: A pass runs only where some cluster could be kept: where its pixels' Σ ||r||² lies further above
#: the least a re-fit reaches under the fit's residual variance ((m - p) σ̂², less this many
#: standard deviations of that χ²) than the cluster's threshold.
NOISE_DEVIATIONS = 3.0


def repair_region(
    flagged: Bool[np.ndarray, " T"], allowed: Bool[np.ndarray, " T"], shape: tuple[int, int],
) -> Bool[np.ndarray, " T"]:
    """The texels a repair moves: the flagged ones and their eight neighbours on the (H, W) grid
    (those a pixel's bilinear taps read together with them; across the map's edges too, as a
    repeating wrap reads them, whatever the fit's wrap: a texel freed for nothing keeps its value
    or is put back by `improved_clusters`), where ``allowed``."""
    h, w = shape
    grown = ndimage.maximum_filter(np.asarray(flagged, bool).reshape(h, w), size=3, mode="wrap")
    return grown.reshape(-1) & np.asarray(allowed, bool)


def fill_from_nearest(
    x: Float[np.ndarray, "T K"], flagged: Bool[np.ndarray, " T"], sources: Bool[np.ndarray, " T"],
    shape: tuple[int, int], free: Float[np.ndarray, "T K"],
) -> Float[np.ndarray, "T K"]:
    """x with each flagged texel's free channels copied from the nearest source texel (Euclidean
    distance on the (H, W) grid, ties as `scipy.ndimage.distance_transform_edt` breaks them).
    ``x`` may have rows past the map's H W (padding); they are kept. With no source, x."""
    h, w = shape
    t = h * w
    flagged = np.asarray(flagged[:t], bool)
    sources = np.asarray(sources[:t], bool) & ~flagged
    if not np.any(sources) or not np.any(flagged):
        return np.array(x, copy=True)
    _, (rows, cols) = ndimage.distance_transform_edt(~sources.reshape(h, w), return_indices=True)
    nearest = (rows * w + cols).reshape(-1)
    y = np.array(x, copy=True)
    moved = flagged[:, None] & (np.asarray(free[:t]) > 0)
    y[:t] = np.where(moved, y[nearest], y[:t])
    return y


def improved_clusters(
    moving: Bool[np.ndarray, " T"], before: Float[np.ndarray, "P C"], after: Float[np.ndarray, "P C"],
    index: Int[np.ndarray, "R 4"], weight: Float[np.ndarray, "R 4"], samples: int, margin: float = 0.0,
    spread: float = 0.0, dof: Optional[Int[np.ndarray, " T"]] = None, noise: float = 0.0,
) -> tuple[Bool[np.ndarray, " T"], int, int]:
    """(the moving texels whose cluster's pixels fit better after than before, by more than
    ``margin`` + ``spread`` √(2 p) in Σ ||r_p||² (p: the sum of ``dof``, each texel's free
    channels (default 1 each), over the cluster), the number of clusters, how many of them fit
    better).

    A cluster is a connected component of the graph on the moving texels that joins two texels
    where one pixel reads both (any sample, any bilinear tap with positive weight): clusters share
    no pixel, so with the other texels held, a cluster's pixels change with it alone and each is
    judged by Σ ||r_p||² over the pixels that read it, ``before`` and ``after`` per pixel.

    ``after`` None asks whether a re-fit could keep any cluster at all: a cluster's Σ ||r||² after
    is then the least a fit of its m residuals and p free channels reaches under noise of variance
    ``noise``, (m - p) ``noise`` less `NOISE_DEVIATIONS` times the spread of that χ², √(2 (m - p))
    ``noise`` (0 with no noise: no bound but 0)."""
    moving = np.asarray(moving, bool)
    t = moving.shape[0]
    rows = index.shape[0]
    reads = (np.asarray(weight) > 0) & moving[np.asarray(index)]
    row, tap = np.nonzero(reads)
    pixel, texel = row // samples, np.asarray(index)[row, tap]
    if texel.size == 0:
        return np.zeros(t, bool), 0, 0
    num_pixels = (rows + samples - 1) // samples
    incidence = sparse.csr_matrix((np.ones(texel.size), (pixel, texel)), shape=(num_pixels, t))
    linked = (incidence.T @ incidence).tocsr()
    _, label = csgraph.connected_components(linked, directed=False)
    # moving texels' labels, renumbered 0..n-1 (texels no pixel reads stay out)
    read = np.zeros(t, bool)
    read[texel] = True
    cluster = np.full(t, -1)
    ids, cluster[read] = np.unique(label[read], return_inverse=True)
    n = len(ids)
    pixel_cluster = np.full(num_pixels, -1)
    pixel_cluster[pixel] = cluster[texel]
    on = pixel_cluster >= 0
    err = lambda r: np.sum(np.square(np.asarray(r, np.float64)[:num_pixels]), axis=1)[on]
    dof = np.ones(t) if dof is None else np.asarray(dof, np.float64)
    p = np.bincount(cluster[read], weights=dof[read], minlength=n)
    e_before = np.bincount(pixel_cluster[on], weights=err(before), minlength=n)
    if after is None:
        m = np.asarray(before).shape[1] * np.bincount(pixel_cluster[on], minlength=n)
        left = np.maximum(m - p, 0.0)
        e_after = np.maximum(left - NOISE_DEVIATIONS * np.sqrt(2.0 * left), 0.0) * noise
    else:
        e_after = np.bincount(pixel_cluster[on], weights=err(after), minlength=n)
    threshold = margin + spread * np.sqrt(2.0 * p)
    better = e_after < e_before - threshold
    return read & better[np.maximum(cluster, 0)], n, int(np.sum(better))


def evidence_variance(energy: float, residual_count: int, parameter_count: int, scale: float) -> float:
    """The residual variance the outlier pass weighs a cluster's gain in: σ̂² =
    `pbrfit.fitting.uncertainty.residual_variance`, but at least `MISFIT_FLOOR` × ``scale`` (the images'
    mean squared value). Below that floor the residuals are an exact fit's float32 rounding, not
    noise, and a cluster re-solved into another rounding of the same fit is put back (on the
    noiseless peer scene, without the floor, 151 texels were kept for a gain of 1.430e-11 to
    1.421e-11)."""
    return max(residual_variance(energy, residual_count, parameter_count), MISFIT_FLOOR * scale)


def search_problem(region: Problem, pixels: Int[np.ndarray, " N"], key, compiler) -> tuple:
    """(problem, key, texels) of a repair's search over ``region`` (``key`` its `search_inputs`
    key): ``region`` itself (texels None), or ``region`` over ``pixels`` alone (the pixels of the
    texels it moves, `moving_pixels`) padded to 1/2, 1/4, ... of its pixels (`take_pixels`) and
    over the texels those read (`take_texels`, ``texels`` which of ``region``'s each is),
    whichever costs least: a search's time in proportion to its pixels, plus
    `SEARCH_COMPILE_COST` (at most `SEARCH_COMPILE_PIXELS`) where its size's program is not
    compiled yet. The pixels left out read no texel that moves, so both search alike; their
    programs do not."""
    total = region.num_pixels
    sizes = halving_sizes(total, len(pixels), mesh_size(region))
    if len(sizes) == 1:
        return region, key, None
    # the texels taken do not depend on the size: the smallest's problem gives every size's key,
    # its texels padded to a count whose program is compiled where there is one (`texel_program`)
    least, least_texels = take_texels(take_pixels(region, pixels, sizes[-1]))
    # a size's key: the search's (its name, the map's shape, whether classes share no pixel), the problem's
    programs = [(None, key)] + [texel_program(region, least, lambda p, n=size: key[:3] + problem_key(p, n),
                                              compiler.has) for size in sizes[1:]]
    compile_cost = min(SEARCH_COMPILE_COST, SEARCH_COMPILE_PIXELS / total)
    cost = [size / total + (0.0 if compiler.has(k) else compile_cost) for size, (_, k) in zip(sizes, programs)]
    best = int(np.argmin(cost))
    if best == 0:
        return region, key, None
    count, program = programs[best]
    if best == len(sizes) - 1 and count == least.num_texels:
        return least, program, least_texels
    sub, texels = take_texels(take_pixels(region, pixels, sizes[best]), size=count)
    return sub, program, texels


def repair_skipped(solver, final, channels) -> Optional[str]:
    """Why the basin repair does not apply to a fit, or None where it does."""
    if tuple(final) == (1, 1):
        return "a uniform material"
    if not is_structured(solver):
        return f"needs the {DEFAULT_SOLVER} solver"
    if not np.any(np.asarray(channels) > 0):
        return "no channel is fitted"
    return None


def run_repair(runner, compiler, problem: Problem, xs, linearization, shape, seen, channels, num_free: int,
               where: dict, search_on: Optional[Problem] = None):
    """Texels the solve left in a wrong basin, started again from their neighbours
    (`pbrfit.fitting.stages.repair`): (x, linearisation, report). Each pass flags texels, copies into them the
    nearest unflagged one's values, runs the coordinate search and `REPAIR_STEPS` steps over the
    flagged texels and their neighbours (all others held), puts back the clusters whose pixels do
    not fit better (`improved_clusters`), and is kept where the objective then falls. The misfit
    passes flag the well-seen identifiable texels whose pixels fit worse than the noise explains
    (`misfit_texels`) and go on while one lowers the objective by more than `REPAIR_PROGRESS`, up
    to `REPAIR_PASSES`; then one pass flags the identifiable texels out of line with their
    neighbours (`outlier_texels`) and keeps a cluster only where its pixels' Σ ||r||² fell by more
    than (`OUTLIER_EVIDENCE` + `OUTLIER_SPREAD` √(2p)) residual variances (`evidence_variance`),
    p its free channels. Each report entry's "kind" says which. ``search_on``: the problem the
    searches run on, the fit's own search's (pixel centres where the fit's samples have them, the
    steps and the judging still on ``problem``); None: ``problem``. On the noisy flash scene (2 × 2
    samples) the outlier pass searched half the samples' pixels, with a 2.1 s compile of its own;
    at the centres, with the program the fit's search compiled, ``times["repair"]`` is 3.0 s
    against 7.1 s (experiments/speed.md)."""
    t = shape[0] * shape[1]
    seen_t = np.asarray(seen[:t], bool)
    obs = problem.obs
    scale = float(np.mean(np.square(np.asarray(obs.pixel_rows(obs.target), np.float64))))
    index, weight, free = np.asarray(problem.index), np.asarray(problem.weight), np.asarray(problem.free)
    fitted = np.asarray(channels) > 0
    searching = problem if search_on is None else search_on
    s_index, s_weight, s_free = ((index, weight, free) if searching is problem else (
        np.asarray(searching.index), np.asarray(searching.weight), np.asarray(searching.free)))
    key, classes, static = search_inputs(shape, searching, REPAIR_ROUNDS, channels[3] > 0)
    xs = np.asarray(xs, np.float32)
    energy = problem_energy(linearization[0], xs, problem)
    passes = []

    def judged():
        """(misfit flags, well-seen identifiable texels, identifiable texels) at the current
        linearisation."""
        r, jac = linearization
        mean, count = texel_misfit(np.asarray(r), index, weight, problem.samples, problem.num_texels)
        blocks = np.asarray(jitted_normal_blocks(jac, problem))[:t]
        identifiable = identifiable_texels(blocks, fitted, seen_t)
        trusted = well_seen_texels(count[:t], seen_t) & identifiable
        return misfit_texels(mean[:t], count[:t], seen_t, scale) & trusted, trusted, identifiable

    def run_pass(kind, flagged, trusted, margin, spread=0.0):
        """One pass over ``flagged``: its report entry appended, and whether it was kept."""
        nonlocal xs, linearization, energy
        entry = dict(kind=kind, flagged=int(np.sum(flagged)))
        passes.append(entry)
        if not np.any(flagged):
            return False
        moving = np.zeros(problem.num_texels, bool)
        moving[:t] = repair_region(flagged, trusted, tuple(shape))
        dof = np.sum(free > 0, axis=1)
        if margin > 0:  # a cluster is kept only where its pixels' Σ ||r||² falls by more than its
            # threshold, so not where Σ ||r||² is within that of what the noise leaves: such a pass
            # is not run (on the noiseless flash scene, a 16-bit capture fitted to its rounding: 23 s)
            noise = residual_variance(energy, 3 * obs.num_pixels, num_free)
            _, clusters, possible = improved_clusters(moving, linearization[0], None, index, weight, problem.samples,
                                                      margin, spread, dof, noise)
            if not possible:
                entry.update(moved=0, clusters=clusters, clusters_kept=0, texels_kept=0, energy_before=energy,
                             energy_after=energy, steps=0, kept=False,
                             skipped="no cluster's pixels misfit by more than noise and the evidence threshold")
                return False
        region_free = free * moving[:, None]
        region = dataclasses.replace(problem, free=jax.device_put(region_free, problem.free.sharding))
        y = fill_from_nearest(xs, flagged, trusted, tuple(shape), free)
        where["repair"] = len(passes)
        searched = region if searching is problem else dataclasses.replace(searching, free=jax.device_put(
            s_free * region_free, searching.free.sharding))  # free where both are
        searched, search_key, texels = search_problem(
            searched, moving_pixels(moving, s_index, s_weight, searching.samples), key, compiler)
        entry.update(searched_pixels=searched.num_pixels, searched_samples=searched.samples,
                     searched_texels=searched.num_texels)
        if texels is None:
            y = timed(compiler, search_key, coordinate_search, "repair", to_device(y, np.float32), searched,
                      classes, *static)
        else:
            found = timed(compiler, search_key, coordinate_search, "repair",
                          to_device(texel_rows(y, texels), np.float32), searched,
                          to_device(texel_rows(classes, texels)), *static)
            y = set_texel_rows(np.asarray(y, np.float32), texels, found)
        y, info = runner.refit(to_device(y, np.float32), region, moving, REPAIR_STEPS, num_free, linearization)
        # residuals and pixel Jacobians do not depend on which texels move: the full problem's
        after = runner.linearization
        better, clusters, improved = improved_clusters(moving, linearization[0], after[0], index, weight,
                                                       problem.samples, margin, spread, dof)
        z = np.asarray(y, np.float32)
        if improved and not np.array_equal(better, moving):
            # the other clusters back where they were: where their pixels read no texel kept (clusters
            # share no pixel), those pixels' rows are the start's; else linearised there (step 0)
            z = np.where(better[:, None], z, xs)
            back = moving_pixels(moving & ~better, index, weight, problem.samples)
            if np.intersect1d(back, moving_pixels(better, index, weight, problem.samples)).size:
                runner(to_device(z, np.float32), problem, 0, num_free)
                after = runner.linearization
            else:
                after = pixel_rows_from(linearization, back, after, problem.samples)
        where.pop("repair")
        e_after = problem_energy(after[0], z, problem)
        kept = improved > 0 and e_after < energy
        entry.update(moved=int(np.sum(moving)), clusters=clusters, clusters_kept=improved if kept else 0,
                     texels_kept=int(np.sum(better)) if kept else 0, energy_before=energy, energy_after=e_after,
                     steps=info["steps"], kept=bool(kept))
        if kept:
            xs, linearization, energy = z, after, e_after
        return kept

    misfit, trusted, identifiable = judged()
    for _ in range(REPAIR_PASSES):
        if not np.any(misfit):
            break
        before = energy
        if not run_pass("misfit", misfit, trusted, 0.0):
            break  # nothing moved: the flags below are those at hand
        misfit, trusted, identifiable = judged()
        if before - energy <= REPAIR_PROGRESS * before:
            break
    # the material channels only: a normal map's slopes span a wider range, and bump detail is out
    # of line with its neighbours by nature. Well seen or not: a wrong basin hides in a corner
    # that few pixels read as well.
    material = fitted & (np.arange(fitted.size) < len(CHANNELS))
    sigma2 = evidence_variance(energy, 3 * obs.num_pixels, num_free, scale)
    run_pass("outliers", outlier_texels(xs[:t], material, identifiable, tuple(shape)), identifiable,
             OUTLIER_EVIDENCE * sigma2, OUTLIER_SPREAD * sigma2)
    return xs, linearization, dict(passes=passes)
