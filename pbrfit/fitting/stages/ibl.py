"""Which model of the environment light a capture needs: the split sum or per-pixel integrals.

The split sum (`pbrfit.lighting.ibl`) is the model of pbrfit's own renders and costs nothing
before the solve; against a path tracer it is 2-3% off under smooth light and tens of percent
off under a sun, where rough metals and grazing views see a lobe it does not model (docs/ibl.md).
Per-pixel integrals (`pbrfit.lighting.pixel_ibl`) integrate each pixel's own lobe, with the
mesh's occlusion of the environment where it has any, at the price of a Monte Carlo integration
per pixel before the solve. ``fit(..., ibl="auto")`` (the default) fits with the split sum first
and tests that fit's residuals for what noise never shows and the split sum's error does:
structure shared by neighbouring pixels.

Over every pair of horizontally or vertically neighbouring fitted pixels, per colour channel,
with residuals r = I - R (image minus the fitted render):

    c = mean(r_a r_b),    s = mean((r_a² + r_b²) / 2),    ρ = c / s,

ρ the residuals' neighbour correlation (noise: about 0, a little below since the maps absorb
some of it; a lighting model's error changes slowly over the surface and is shared). The
*structured share* √max(c, 0) / mean|I| is the RMS of the part neighbours share, relative to
the images' mean value, and z = ρ √pairs tests ρ against white noise. Where the share is at
least `MISFIT_SHARE` at z ≥ `MISFIT_Z`, the fit runs again with per-pixel integrals, and the
one whose residual σ is lower is kept (`per_pixel_explains_better`): a false call costs time,
not accuracy.

Measured on split-sum fits at pixel centres (docs/ibl.md, "The default: split sum or per-pixel
integrals"; the Mitsuba captures are `experiments/pathtraced.md`'s):

| capture | ρ | share |
| --- | --- | --- |
| pbrfit's split-sum renders, 1% noise (demo, sphere-floor) | −0.018, −0.015 | 0 |
| pbrfit's noiseless split-sum render (sphere-env) | 0.40 | 0.0009 |
| pbrfit's 2 × 2 supersampled render (the footprint's own misfit) | 0.09 | 0.013 |
| Mitsuba, sphere / torus on a floor under sun and sky, depth 4 | 0.85 / 0.73 | 0.29 / 0.34 |

With occlusion, per-pixel integrals also model light reflected between surfaces: a blocked
direction brings the radiance the capture shows where it lands (`pbrfit.lighting.visibility`).
Photographs and path tracers' renders hold that light, renders of direct light only (pbrfit's
Monte Carlo reference, a path tracer at max_depth 2) do not; with ``bounce="auto"`` (the default)
the per-pixel fit runs both ways and keeps the bounce where it explains the images clearly
better (`bounce_explains_better`).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MISFIT_SHARE", "MISFIT_Z", "AUTO_MAX_IBL_PIXELS", "misfit_evidence", "split_sum_misfits",
           "per_pixel_skipped", "fit_sigma", "per_pixel_explains_better", "BOUNCE_MIN_GAIN", "bounce_explains_better"]

#: Least structured share (`misfit_evidence`) that sends a fit to per-pixel integrals: above the
#: footprint's own misfit (0.013), far below a path tracer's under a sun (0.29-0.34).
MISFIT_SHARE = 0.05
#: Least z of the neighbour correlation that does.
MISFIT_Z = 3.0
#: The most rows (pixels, or pixel samples: the footprint's 2 × 2 samples and their centres are
#: five a pixel, its 3 × 3 on linear images ten) "auto" integrates per pixel unasked: the
#: integrals take about 2.5 ms a row on a 2-core CPU at the default 512 samples (docs/ibl.md),
#: about 10 minutes here; beyond it the fit keeps the split sum (or, once per-pixel integrals are
#: chosen, the pixel centres) and says why (``ibl="per_pixel"``, ``pixel_samples=2`` integrate
#: them, best on a GPU).
AUTO_MAX_IBL_PIXELS = 250_000


def misfit_evidence(images, targets, masks) -> dict:
    """How much of a fit's residuals neighbouring pixels share (module docstring): per view the
    fitted render R (H, W, 3), the image I and the fitted pixels' mask (H, W). Returns the
    neighbour correlation ``rho``, its ``z``, the structured ``share`` and the ``pairs`` used
    (0 of each where no two neighbours were fitted)."""
    num = den = level = 0.0
    pairs = values = 0
    for image, target, mask in zip(images, targets, masks):
        image, target = np.asarray(image, np.float64), np.asarray(target, np.float64)
        mask = np.asarray(mask, bool)
        r = target - image
        level += float(np.sum(np.abs(target[mask])))
        values += 3 * int(np.sum(mask))
        for a, b, both in ((r[:, :-1], r[:, 1:], mask[:, :-1] & mask[:, 1:]),
                           (r[:-1], r[1:], mask[:-1] & mask[1:])):
            num += float(np.sum(a[both] * b[both]))
            den += float(np.sum(a[both] ** 2 + b[both] ** 2)) / 2
            pairs += 3 * int(np.sum(both))
    if pairs == 0 or den <= 0.0 or level <= 0.0:
        return dict(rho=0.0, z=0.0, share=0.0, pairs=pairs)
    rho = num / den
    share = math.sqrt(max(num / pairs, 0.0)) / (level / values)
    return dict(rho=float(rho), z=float(rho * math.sqrt(pairs)), share=float(share), pairs=pairs)


def split_sum_misfits(evidence: dict) -> bool:
    """Whether `misfit_evidence` of a split-sum fit shows light the split sum cannot model: a
    structured share of at least `MISFIT_SHARE` at z ≥ `MISFIT_Z`."""
    return evidence["share"] >= MISFIT_SHARE and evidence["z"] >= MISFIT_Z


def per_pixel_skipped(rows: int) -> str | None:
    """Why "auto" does not integrate ``rows`` rows per pixel unasked (more than
    `AUTO_MAX_IBL_PIXELS`), or None."""
    if rows <= AUTO_MAX_IBL_PIXELS:
        return None
    return (f"{rows:,} pixel rows to integrate > AUTO_MAX_IBL_PIXELS ({AUTO_MAX_IBL_PIXELS:,}); "
            "--ibl per_pixel or --pixel-samples 2 integrates them")


def fit_sigma(report: dict) -> float:
    """A fit's residual σ in the images' own units: with ``noise_level="estimated"`` the first,
    unweighted fit's (the second weighs each fit's residuals by its own noise estimate, which
    would favour the model whose misfit it took for noise)."""
    first = (report.get("noise_level") or {}).get("first_fit")
    return float(first["residual_sigma"] if first else report["residual_sigma"])


def per_pixel_explains_better(split_sum_report: dict, per_pixel_report: dict) -> bool:
    """Of two fits of the same capture, one per model of the environment light: whether the
    per-pixel integrals' residual σ is the lower (ties go to the cheaper split sum). Both fit
    the same parameters to the same pixel values, so that is the likelier model."""
    return fit_sigma(per_pixel_report) < fit_sigma(split_sum_report)


#: The bounce's fit (`pbrfit.lighting.visibility.Bounce`) is kept where its residual σ is at least
#: this share below the fit with the blocked directions dark. It adds light, which a fitted
#: material can partly absorb, so a tie goes to the dark fit: on the Mitsuba captures of
#: experiments/pathtraced.md the bounce's σ is 0.02% and 0.9% higher at max_depth 2 (direct light
#: only) and 8.0% and 4.6% lower at max_depth 4; on pbrfit's Monte Carlo sphere on a floor (direct
#: light only) 26% higher.
BOUNCE_MIN_GAIN = 0.01


def bounce_explains_better(dark_report: dict, bounce_report: dict) -> bool:
    """Of two fits of the same capture with the same per-pixel integrals, whether the one whose
    blocked directions bring the bounce's light explains the images better than the one where they
    are dark: its residual σ lower by `BOUNCE_MIN_GAIN`."""
    return fit_sigma(bounce_report) < (1.0 - BOUNCE_MIN_GAIN) * fit_sigma(dark_report)
