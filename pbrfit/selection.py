"""Model selection: one value instead of a map where the images do not support the map.

A channel fitted as a map of T texels has T parameters; held at one common value it has one.
Where the images cannot tell that channel's texels apart (a dielectric plane's metallic under
noise, the roughness of a surface no highlight reaches twice), the map fits the noise: its
texels scatter about the truth by their standard errors σ_t, and through the channels they are
correlated with (base colour with metallic) they drag the others along. One value fitted from
every pixel has no such scatter, but errs by the truth's own spread about its mean.

Akaike's information criterion (H. Akaike, "A new look at the statistical model
identification", IEEE Trans. Automatic Control 19(6), 1974) weighs the two: with Gaussian
residuals it is 2E/σ² + 2·(parameters), for the data term E = ½ Σ r². The common value is kept
when

    Δ = 2 (E_uniform − E_map) / σ̂²  ≤  2 (T − 1),

σ̂² the map fit's residual variance (`pbrfit.uncertainty.residual_variance`). For nested
least-squares models Δ's expectation is (T − 1) + Σ_t (m_t − m̄)² / σ_t² (its degrees of freedom
plus the non-centrality of the true map m about its mean), so the test keeps the common value
when the truth's spread about its mean is below the map's own noise: when the common value is
the smaller error too.

The common value is the profile-likelihood estimate: the other channels re-fitted at each
trial value c, Newton steps on c with

    dE_uniform/dc = Σ_t ∂E/∂x_tc   (the envelope theorem: the others are at their optimum),
    d²E_uniform/dc² ≈ Σ_t s_t,    s_t = 1 / [(D_t)⁻¹]_cc,

D_t the texel's Gauss-Newton block over the fitted channels (`pbrfit.solvers.normal_blocks`)
and s_t the Schur complement of channel c in it (its curvature with the texel's other channels
re-fitted), projected onto the channel's bounds. Its standard error is sqrt(σ̂² / Σ_t s_t).

Before any re-fit, a Wald statistic W = Σ_t s_t (x_t − c₀)² / σ̂² of the map's own values about
their precision-weighted mean c₀ approximates Δ; a map with W above `WALD_MARGIN` times the
threshold is kept without re-fitting (a textured map, nearly always).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SELECTABLE", "WALD_MARGIN", "NEWTON_STEPS", "aic_statistic", "prefers_uniform", "profile_precision",
           "wald_statistic", "weighted_value", "newton_value"]

#: Channels the test may make uniform: (name, channel index). Base colour is always a map.
SELECTABLE = (("metallic", 3), ("roughness", 4))
#: A map whose Wald statistic is above this multiple of the test's threshold is kept unchallenged.
WALD_MARGIN = 4.0
#: Newton steps on the common value (each one re-fit of the other channels).
NEWTON_STEPS = 3


def profile_precision(blocks: np.ndarray, channels: np.ndarray, seen: np.ndarray, c: int) -> np.ndarray:
    """(T,) s_t = 1 / [(D_t)⁻¹]_cc over the fitted channels: channel c's curvature in texel t
    with the texel's other fitted channels re-fitted (the Schur complement); 0 for unseen texels
    and for blocks singular in c (pseudo-inverse: a channel no pixel constrains adds nothing)."""
    blocks = np.asarray(blocks, np.float64)
    free = np.asarray(channels, bool)
    idx = np.flatnonzero(free)
    pos = int(np.flatnonzero(idx == c)[0])
    sub = blocks[:, idx[:, None], idx[None, :]]
    inv = np.linalg.pinv(sub, rcond=1e-10, hermitian=True)
    var = inv[:, pos, pos]
    s = np.where(var > 0, 1.0 / np.where(var > 0, var, 1.0), 0.0)
    return np.where(np.asarray(seen, bool), s, 0.0)


def weighted_value(values: np.ndarray, precision: np.ndarray, lo: float, hi: float) -> float:
    """The precision-weighted mean of a channel's texel values, within [lo, hi] (the plain mean
    where no texel has any precision)."""
    values = np.asarray(values, np.float64)
    w = np.asarray(precision, np.float64)
    mean = float(np.sum(w * values) / np.sum(w)) if np.sum(w) > 0 else float(np.mean(values))
    return float(np.clip(mean, lo, hi))


def wald_statistic(values: np.ndarray, precision: np.ndarray, value: float, sigma2: float) -> float:
    """W = Σ_t s_t (x_t − c)² / σ̂²: the squared distance of the map from one value, in units of its
    standard errors (the test statistic's approximation from the map fit alone)."""
    d = np.asarray(values, np.float64) - value
    return float(np.sum(np.asarray(precision, np.float64) * d * d) / max(sigma2, np.finfo(np.float64).tiny))


def newton_value(value: float, gradient_sum: float, precision_sum: float, lo: float, hi: float) -> float:
    """One projected Newton step on the common value: clip(c − Σ g / Σ s, lo, hi)."""
    if not precision_sum > 0:
        return value
    return float(np.clip(value - gradient_sum / precision_sum, lo, hi))


def aic_statistic(loss_uniform: float, loss_map: float, sigma2: float) -> float:
    """Δ = 2 (E_uniform − E_map) / σ̂², E = ½ Σ r² of each fit."""
    return 2.0 * (float(loss_uniform) - float(loss_map)) / max(sigma2, np.finfo(np.float64).tiny)


def prefers_uniform(statistic: float, texels: int) -> bool:
    """Akaike's choice: the common value where Δ ≤ 2 (T − 1) for a map of T free texels."""
    return statistic <= 2.0 * (texels - 1)
