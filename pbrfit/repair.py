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
2. `fill_from_nearest`: each flagged texel takes the fitted values of the nearest texel that is
   seen and not flagged (the basin of the patch around it).
3. The fit's coordinate search (`pbrfit.initialisation.coordinate_search`, `REPAIR_ROUNDS`
   sweeps) and `REPAIR_STEPS` solver steps follow (`pbrfit.fit`), and the result is kept only
   where its objective is lower than before the repair; up to `REPAIR_PASSES` passes while each
   is kept.

`texel_misfit` is the host-side twin of `pbrfit.initialisation._texel_scores` (divided by the
count): it runs once per pass on the solver's residuals, where a jitted scatter would add a
compile to every fit.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy import ndimage

__all__ = ["MISFIT_FACTOR", "MISFIT_FLOOR", "REPAIR_ROUNDS", "REPAIR_STEPS", "REPAIR_PASSES", "texel_misfit",
           "misfit_texels", "fill_from_nearest"]

#: A texel is flagged where its mean squared residual exceeds this many times the median.
MISFIT_FACTOR = 10.0
#: ... and this fraction of the mean squared target value (an exact fit's float32 rounding
#: leaves about 1e-14 of it).
MISFIT_FLOOR = 1e-8
#: Sweeps of the coordinate search in a repair (one sweep leaves texels whose neighbours the
#: sweep moved after them: on the peer scene's seed 3, roughness RMSE 0.013 after one, exact
#: after two).
REPAIR_ROUNDS = 2
#: Solver steps after a repair's search.
REPAIR_STEPS = 20
#: Most repair passes per fit (each runs only where the one before it was kept).
REPAIR_PASSES = 3


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
