"""The images' noise level as a function of the pixel value, and the residual weights it gives.

Plain least squares weighs every residual alike, which is the maximum-likelihood fit when every
value carries the same noise (read noise, quantisation). A camera's noise grows with the signal:
shot noise has variance proportional to it, and a gain or a compression step can make the
standard deviation proportional (noise "of 1% of the value"). Then the bright pixels, highlights
first, count for more than their precision, the fit is not the likeliest one, and one residual
variance σ̂² cannot describe every pixel, so the standard errors are off too
(experiments/uncertainty.md: under noise of 1% of each value, base colour's σ came out 1.5 times
the scatter of repeated fits).

`fit(..., noise_level="estimated")` therefore fits twice. The first fit's residuals r and
fitted values v̂ (in the images' own space: display values for sRGB files) give the noise level
function σ(v) (`estimate_noise_level`): the residual components, pooled over colour channels,
are sorted by their fitted value into `NOISE_BINS` bins of equal count, and each bin's variance
is estimated robustly as median(r²) / `MEDIAN_CHI2` (the median of a squared standard normal),
so that a cluster of texels the fit left in a wrong basin does not inflate it. A smooth shape
a + b v + c v² (a, b, c >= 0: read noise, shot noise, noise proportional to the value) is fitted
to the bins, the bins are measured once more relative to it (which takes out the level's change
within a bin), and σ²(v) is the bins' variances interpolated in proportion to the shape between
them, and the shape times the end bins' ratios to it beyond them (`NoiseLevel`): a
non-parametric noise level function (as in C. Liu et al., "Automatic estimation and removal of
noise from a single image", IEEE TPAMI 2008, there per intensity bin of the image itself) that
follows the shape into the darkest and brightest values. The
second fit, started from the first, weighs each value's residual by w = σ_ref / σ(v̂)
(`NoiseLevel.weights`), σ_ref the median of σ(v̂) over the residuals, so that the weights' median
is 1 and the loss keeps its scale: weighted least squares with estimated weights ("feasible
generalised least squares"; e.g. R. J. Carroll and D. Ruppert, "Transformation and Weighting in
Regression", 1988, chapter 2). The weights are fixed during the second fit: they depend on the
first fit's values, not on the ones being fitted (weighing by the targets' own level would bias
the fit, since a value that noise made brighter would count less).

A value the first fit left dark can have a tiny estimated noise (noise proportional to the value
vanishes at 0), and its weight would let renderer approximations there, not noise, decide the
fit. σ(v) is therefore held at or above `NOISE_FLOOR` × σ_ref: no residual weighs more than
1 / `NOISE_FLOOR` times the median.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float

from .defaults import NOISE_LEVELS

__all__ = ["NOISE_LEVELS", "NOISE_BINS", "NOISE_FLOOR", "MEDIAN_CHI2", "MIN_BIN_COUNT", "SHAPE_FIT_FLOOR",
           "SHAPE_SCALE_FLOOR", "NoiseLevel", "estimate_noise_level"]

#: Bins of the noise level function (equal counts of residual components).
NOISE_BINS = 16
#: Fewest residual components per bin: fewer bins where the fit has fewer residuals.
MIN_BIN_COUNT = 200
#: Median of χ²₁ (a squared standard normal): median(r²) / MEDIAN_CHI2 estimates σ².
MEDIAN_CHI2 = 0.454936423119572
#: Lowest noise level, relative to the median one (the largest weight is 1 / NOISE_FLOOR).
NOISE_FLOOR = 0.1
#: In the shape's fit, relative to the bins' variances, a bin's variance counts as at least this
#: fraction of the largest: a bin of exact residuals (variance 0) would otherwise weigh infinitely.
SHAPE_FIT_FLOOR = 1e-6
#: Where the second pass divides the squared residuals by the shape's variance, that variance is
#: held at or above this fraction of its largest (a shape c v² vanishes at v = 0).
SHAPE_SCALE_FLOOR = 1e-12
#: Per bin, how much lower (in squared relative misfit) a subset of the shape's terms must fit
#: to be preferred to a simpler one tried before it: exact fits differ by round-off only.
_SHAPE_TIE = 1e-12


def _shape_variance(shape, v):
    """The shape's variance a + b v + c v² at v, for ``shape`` = (a, b, c)."""
    a, b, c = (float(t) for t in shape)
    return a + b * v + c * v * v


@dataclasses.dataclass(frozen=True)
class NoiseLevel:
    """A noise level function σ(v) of the value v in the images' own space.

    σ²(v) = s(v) V(v) / S(v), with a smooth shape s(v) = a + b v + c v² (read noise, shot
    noise, noise proportional to the value; a, b, c >= 0) and V, S the linear interpolations of
    the bins' measured variances and of the shape's variances at the bins (held beyond the end
    bins). At a bin it is the bin's variance; between two it follows the shape's curvature and,
    s being convex, stays at or below the straight line between their variances (the shape times
    the interpolated ratio V / S would overshoot both bins where one of them fits the shape
    badly); beyond the end bins it is the shape times their ratio, so where the shape is the
    noise's law σ(v) follows that law into the darkest and brightest values. σ is floored at
    `NOISE_FLOOR` σ_ref.

    Attributes:
        values: (B,) increasing values at which the level was measured (each bin's median).
        sigma: (B,) the noise standard deviation there.
        shape: (3,) the shape's (a, b, c); zero where no residual is non-zero.
        reference: σ_ref, the median level over the residuals it was estimated from; weights
            are σ_ref / σ(v).
    """

    values: np.ndarray
    sigma: np.ndarray
    shape: np.ndarray
    reference: float

    def __call__(self, v) -> np.ndarray:
        """σ(v) = sqrt(s(v) V(v) / S(v)), at least `NOISE_FLOOR` σ_ref."""
        v = np.asarray(v, np.float64)
        at_bins = _shape_variance(self.shape, self.values)
        if np.all(at_bins > 0.0):
            var = (_shape_variance(self.shape, v) * np.interp(v, self.values, np.square(self.sigma))
                   / np.interp(v, self.values, at_bins))
        else:  # no shape (or one that vanishes at a bin): the variances themselves interpolated
            var = np.interp(v, self.values, np.square(self.sigma))
        return np.maximum(np.sqrt(np.maximum(var, 0.0)), NOISE_FLOOR * self.reference)

    def weights(self, v: Float[np.ndarray, "*shape"]) -> Float[np.ndarray, "*shape"]:
        """σ_ref / σ(v) (float32): each residual's factor; median 1 over the fit's values (1 at a
        value that is not a number)."""
        with np.errstate(invalid="ignore"):
            w = self.reference / self(v)
        return np.where(np.isnan(w), 1.0, w).astype(np.float32)

    def describe(self) -> dict:
        """JSON-ready: the bins' values and levels, the shape, the reference level and the floor."""
        return dict(values=[float(v) for v in self.values], sigma=[float(s) for s in self.sigma],
                    shape=dict(zip(("constant", "linear", "quadratic"), (float(t) for t in self.shape))),
                    reference_sigma=float(self.reference), floor=NOISE_FLOOR)


def _bin_levels(v, r2, count: int, scale=None):
    """(medians of v, variances) of `count` equal-count bins of the sorted (v, r²): median(r²) /
    `MEDIAN_CHI2` per bin, or with ``scale`` (a first estimate's variance at each v) the bin
    median's scale times median(r² / scale) / `MEDIAN_CHI2`, which takes out the level's change
    within the bin. Bins that share a median v are merged (count-weighted)."""
    centres, levels = [], []
    for part in np.array_split(np.arange(v.size), count):
        c = float(np.median(v[part]))
        if scale is None:
            var = float(np.median(r2[part])) / MEDIAN_CHI2
        else:
            s = scale[part]
            var = float(np.median(r2[part] / s)) / MEDIAN_CHI2 * float(np.median(s))
        if centres and c <= centres[-1]:  # the same value (a flat or quantised stretch): one bin
            var_prev, n_prev = levels[-1]
            levels[-1] = ((var_prev * n_prev + var * part.size) / (n_prev + part.size), n_prev + part.size)
            continue
        centres.append(c)
        levels.append((var, part.size))
    return np.array(centres), np.array([lv for lv, _ in levels])


def _quadratic_shape(values, var):
    """(a, b, c) >= 0 of the variance a + b v + c v² (read noise, shot noise, noise proportional to
    the value) closest to the bins' variances in relative terms, or None where no bin has any
    (the best of the non-negative subsets of the three terms, each by least squares; of subsets
    that fit about as well, the simplest: one bin gives a constant, not a slope that round-off
    happened to favour)."""
    var = np.asarray(var, np.float64)
    if not np.max(var) > 0.0:
        return None
    scale = np.maximum(var, SHAPE_FIT_FLOOR * np.max(var))
    basis = np.stack([np.ones_like(values), values, values * values], axis=1) / scale[:, None]
    target = var / scale
    best, best_cost = None, np.inf
    for subset in ((0,), (1,), (2,), (0, 1), (0, 2), (1, 2), (0, 1, 2)):
        coef, *_ = np.linalg.lstsq(basis[:, subset], target, rcond=None)
        if np.any(coef < 0.0):
            continue
        cost = float(np.sum(np.square(basis[:, subset] @ coef - target)))
        if cost < best_cost - _SHAPE_TIE * len(values):
            best = np.zeros(3)
            best[list(subset)] = coef
            best_cost = cost
    return best


def estimate_noise_level(values, residuals, bins: int = NOISE_BINS, dof_scale: float = 1.0) -> NoiseLevel:
    """The noise level function of residuals r at fitted values v (same shape, any; pooled).

    The components are sorted by v and split into ``min(bins, n // MIN_BIN_COUNT)`` bins of equal
    count (at least one); a bin's variance is median(r²) / `MEDIAN_CHI2` at its median v, then
    once more with each r² divided by a smooth first estimate at its own v (the non-negative
    a + b v + c v² closest to the bins, `_quadratic_shape`) and the bin's variance that ratio's
    median times the estimate's: where the level changes across a bin (the darkest bin of noise
    proportional to the value spans a tenfold range), the plain median lies below the level at
    the bin's median value. Bins that share a median v are merged; the level is
    sqrt(``dof_scale`` × variance). ``dof_scale`` = n / (n - p) corrects for
    the parameters fitted (a least-squares fit's residuals are smaller than its noise by that
    factor on average). Non-finite components are left out.
    """
    v = np.asarray(values, np.float64).reshape(-1)
    r = np.asarray(residuals, np.float64).reshape(-1)
    if v.shape != r.shape:
        raise ValueError(f"values and residuals must have the same size, got {v.size} and {r.size}")
    ok = np.isfinite(v) & np.isfinite(r)
    v, r = v[ok], r[ok]
    if v.size == 0:
        raise ValueError("no finite residual to estimate the noise level from")
    order = np.argsort(v, kind="stable")
    v, r2 = v[order], np.square(r[order])
    count = max(1, min(int(bins), v.size // MIN_BIN_COUNT))
    scale = None
    for _ in range(2):  # the second time relative to the first shape (the level varies within a bin)
        centres, var = _bin_levels(v, r2, count, scale)
        shape = _quadratic_shape(centres, var)
        if shape is None:  # residuals exactly 0: no level to weigh by, so weights of 1
            return NoiseLevel(centres, np.ones_like(var), np.zeros(3), 1.0)
        first = _shape_variance(shape, v)
        scale = np.maximum(first, SHAPE_SCALE_FLOOR * float(np.max(first)))
    sigma = np.sqrt(var * float(dof_scale))
    shape = shape * float(dof_scale)
    reference = float(np.median(NoiseLevel(centres, sigma, shape, reference=0.0)(v)))
    if not reference > 0.0:  # most residuals exactly 0: the floor from the largest level
        reference = float(np.max(sigma))
    return NoiseLevel(centres, sigma, shape, reference)
