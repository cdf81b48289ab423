"""Pixel footprints: which model of a pixel's footprint a fit uses, and how two are compared.

A pixel of a display-referred image (sRGB, tone mapped) is usually the mean of the radiance over
its area (an antialiased render, a photograph), a linear HDR one either. `fit` shades n × n
samples per pixel where asked (`pbrfit.fitting.observations`); with ``pixel_samples="auto"`` it
fits display-referred images both ways and keeps the footprint whose images match better
(`footprint_choice`, `footprint_energies`), and fits linear images at pixel centres, then both ways
(with `AUTO_LINEAR_PIXEL_SAMPLES`) only where those centres' residuals show the box's blur
(`footprint_evidence`, `box_plausible`).
"""

from __future__ import annotations

import math
from typing import Optional

import jax
import numpy as np

from ..observations import MAX_PIXEL_SAMPLES, Observations
from ..objective import Problem, pixel_residuals
from ...transfer import to_device

__all__ = ["footprint_choice", "footprint_energies", "centres_explain_better", "samples_side", "final_residuals",
           "probes_footprint", "footprint_evidence", "box_plausible", "AUTO_PIXEL_SAMPLES", "AUTO_LINEAR_PIXEL_SAMPLES",
           "AUTO_MAX_PIXELS", "BOX_SLOPE", "BOX_Z"]

#: Samples per pixel side that ``pixel_samples="auto"`` tries on display-referred images
#: (`footprint_choice`): 2 × 2 is exact for 2 × 2 supersampled renders and close to finer box
#: averages (experiments/solvers.md, "Pixel footprints").
AUTO_PIXEL_SAMPLES = 2
#: Samples per pixel side for linear images whose pixel-centre fit shows a box footprint
#: (`box_plausible`): path tracers write those, each pixel the mean of thousands of samples over
#: its area, where n × n point samples miss the box by about 1 / n² of its blur for smooth
#: radiance (the midpoint rule), and glints by much more: on Mitsuba's sphere on a floor a 2 × 2
#: render misses a 4 × 4 one by a median 1.7% at bright pixels, and the fit moves the maps to
#: match (experiments/pathtraced.md). 3 × 3 samples take 2.25 times the rows of 2 × 2; a 2 × 2
#: supersampled linear capture (``pbrfit synth --supersample 2``) is then fitted with a model 5/36
#: of the blur off where 2 × 2 would be exact (docs/footprint.md measures both).
AUTO_LINEAR_PIXEL_SAMPLES = 3
#: ... and only on captures of at most this many pixels (all frames together; 16 views of 350²),
#: for both kinds of images: 2 × 2 samples take four times the rows of pixel centres, so about
#: four times the memory and three times the time (3 × 3 on linear images: nine times the rows);
#: beyond it a fit asks for them with ``pixel_samples``.
AUTO_MAX_PIXELS = 2_000_000
#: A centre fit of linear images shows a box footprint (`box_plausible`) where its residuals grow
#: with its render's Laplacian / 24 by at least this slope (1 for a pure box average that the maps
#: cannot absorb) ...
BOX_SLOPE = 0.1
#: ... and the slope is this many standard errors from 0. Measured slopes (`footprint_evidence`,
#: docs/footprint.md): 2 × 2 supersampled and Mitsuba's box-filtered captures 0.22 to 1.26;
#: captures rendered at pixel centres -0.006 to 0.001 (pbrfit's own renders) and 0.06 (Mitsuba's,
#: whose light the model misses in places); but also 1.8 to 2.7 where the model is far from the
#: renderer's (a Monte Carlo render fitted with the split sum, or with one uniform material): its
#: misfit of sharp highlights grows with the Laplacian too. There the fit of both footprints costs
#: time and keeps the one that matches better.
BOX_Z = 3.0


def display_referred(capture) -> bool:
    """Whether any frame holds display values: sRGB-encoded, or tone mapped."""
    return (getattr(capture, "tonemap", "none") != "none"
            or any(f.color_space == "srgb" for f in getattr(capture, "frames", ())))


def image_pixels(capture) -> int:
    """Pixels of all frames together."""
    return int(sum(f.image.shape[0] * f.image.shape[1] for f in getattr(capture, "frames", ())))


def footprint_choice(capture, pixel_samples="auto", views=None) -> tuple[int, bool, Optional[str]]:
    """(n, select, skipped) for `fit`'s ``pixel_samples``: an integer n is taken as given;
    ``"auto"`` gives (`AUTO_PIXEL_SAMPLES`, True) for display-referred images (any frame in
    sRGB, or a tone map), which are photographs or finished renders and so usually pixel
    averages, and (1, False) for linear HDR images, whose centre fit `fit` then tests for a box
    footprint before paying for the samples (`probes_footprint`, `footprint_evidence`); for
    precomputed `views`, which hold pixel centres; and for display-referred captures of more than
    `AUTO_MAX_PIXELS` pixels, for which `skipped` says so (else None). select says to fit both
    footprints and keep the one that explains the images better (`pbrfit.fitting.api.fit_observations`)."""
    if not isinstance(pixel_samples, str):
        return pixel_samples, False, None
    if pixel_samples != "auto":
        raise ValueError(f"pixel_samples must be 'auto' or an integer from 1 to {MAX_PIXEL_SAMPLES}, "
                         f"got {pixel_samples!r}")
    if not display_referred(capture) or views is not None:
        return 1, False, None
    pixels = image_pixels(capture)
    if pixels > AUTO_MAX_PIXELS:
        return 1, False, (f"{pixels:,} image pixels > AUTO_MAX_PIXELS ({AUTO_MAX_PIXELS:,}): pixel centres only; "
                          f"--pixel-samples 2 fits the footprint")
    return AUTO_PIXEL_SAMPLES, True, None


def probes_footprint(capture, pixel_samples="auto", views=None) -> bool:
    """Whether ``pixel_samples="auto"`` tests a pixel-centre fit of `capture` for a box footprint
    (`footprint_evidence`): linear images read from files (not precomputed `views`), of at most
    `AUTO_MAX_PIXELS` pixels."""
    return (pixel_samples == "auto" and views is None and not display_referred(capture)
            and image_pixels(capture) <= AUTO_MAX_PIXELS)


def _laplacian_rows(image: np.ndarray, mask: np.ndarray):
    """(rows of Δ image / 24, the mask of pixels whose 4 neighbours are in `mask` too): the 5-point
    Laplacian, pixel spacing 1, at the pixels where every tap is fitted."""
    inner = np.zeros_like(mask)
    inner[1:-1, 1:-1] = (mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:])
    lap = np.zeros_like(image)
    lap[1:-1, 1:-1] = (image[:-2, 1:-1] + image[2:, 1:-1] + image[1:-1, :-2] + image[1:-1, 2:]
                       - 4.0 * image[1:-1, 1:-1])
    return lap[inner] / 24.0, inner


def footprint_evidence(images, targets, masks) -> dict:
    """How strongly a pixel-centre fit's residuals show a box footprint: per view the fitted
    render R (H, W, 3), the image I and the fitted pixels' mask. A pixel's box average of a
    smooth f is f + (f_xx + f_yy) / 24 + O(h⁴) (pixel size h = 1), so where the images are box
    averages the centres' residuals r = I - R follow Δ R / 24 (the 5-point Laplacian, at pixels
    whose 4 neighbours are fitted), with slope 1 where the maps cannot absorb the blur, and
    scatter about 0 where the images hold pixel centres. Returns the least-squares slope
    β = Σ r ΔR/24 / Σ (ΔR/24)², its z = β sqrt(Σ (ΔR/24)²) / σ (σ the residuals' scale by their
    median absolute deviation; 0 where they are all 0) and the pixel values used."""
    num = den = 0.0
    parts = []
    for image, target, mask in zip(images, targets, masks):
        image, target = np.asarray(image, np.float64), np.asarray(target, np.float64)
        lap, inner = _laplacian_rows(image, np.asarray(mask, bool))
        r = (target - image)[inner]
        num += float(np.sum(r * lap))
        den += float(np.sum(lap * lap))
        parts.append(r.ravel())
    r = np.concatenate(parts) if parts else np.zeros(0)
    if den <= 0.0 or r.size == 0:
        return dict(slope=0.0, z=0.0, values=int(r.size))
    beta = num / den
    sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    z = beta * math.sqrt(den) / sigma if sigma > 0.0 else 0.0
    return dict(slope=float(beta), z=float(z), values=int(r.size))


def box_plausible(evidence: dict) -> bool:
    """Whether `footprint_evidence` shows a box footprint: slope ≥ `BOX_SLOPE` at z ≥ `BOX_Z`. A
    false call costs time, not accuracy: the fit of both footprints keeps the one whose images
    match better."""
    return evidence["slope"] >= BOX_SLOPE and evidence["z"] >= BOX_Z


def centres_explain_better(energies) -> bool:
    """Of (samples' data term, centres' data term, ...): the centres explain the images at
    least as well (ties go to the cheaper model)."""
    return energies[1] <= energies[0]


def samples_side(obs: Observations) -> int:
    """n of the n × n samples per pixel of `obs`."""
    return int(round(math.sqrt(obs.samples)))


def final_residuals(x, problem: Problem, linearization):
    """Pixel residuals at a solver's result: from its linearisation (the structured solver),
    else evaluated (the optimistix solvers return none)."""
    if linearization is not None:
        return linearization[0]
    return jax.jit(pixel_residuals)(to_device(x, np.float32), problem)


def footprint_energies(obs: Observations, residuals, centres: Observations, centre_residuals):
    """The data terms 1/2 Σ_p ||r̃_p||² (the loss: r̃ is the residual transformed by the robust
    loss, the residual itself for l2) of two fits of the same images, one with pixel samples
    (`obs`) and one at pixel centres, summed over the pixels both use (a pixel is usable with
    samples only where all of them hit the mesh): (samples' energy, centres' energy, pixels).
    Both models have the same maps to fit and no other parameter, so the lower energy is the
    likelier footprint (for l2 and Gaussian noise, the higher likelihood)."""

    def per_pixel(o: Observations, r):
        r = np.asarray(r, np.float64)[: o.num_pixels]
        view = np.asarray(o.pixel_rows(o.view_index)).astype(np.int64)
        pix = np.asarray(o.pixel_rows(o.pixel)).astype(np.int64)
        key = view * (1 << 40) + pix
        return key, 0.5 * np.sum(r * r, axis=1)

    ks, es = per_pixel(obs, residuals)
    kc, ec = per_pixel(centres, centre_residuals)
    common, i_s, i_c = np.intersect1d(ks, kc, assume_unique=True, return_indices=True)
    return float(np.sum(es[i_s])), float(np.sum(ec[i_c])), int(common.size)
