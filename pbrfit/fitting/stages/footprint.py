"""Pixel footprints: which model of a pixel's footprint a fit uses, and how two are compared.

A pixel of a display-referred image (sRGB, tone mapped) is usually the mean of the radiance over
its area (an antialiased render, a photograph), a linear HDR one often its centre's. `fit`
shades n × n samples per pixel where asked (`pbrfit.fitting.observations`); with
``pixel_samples="auto"`` it fits display-referred images both ways and keeps the footprint whose
images match better (`footprint_choice`, `footprint_energies`).
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
           "AUTO_PIXEL_SAMPLES", "AUTO_MAX_PIXELS"]

#: Samples per pixel side that ``pixel_samples="auto"`` tries on display-referred images
#: (`footprint_choice`): 2 × 2 is exact for 2 × 2 supersampled renders and close to finer box
#: averages (experiments/solvers.md, "Pixel footprints").
AUTO_PIXEL_SAMPLES = 2
#: ... and only on captures of at most this many pixels (all frames together; 16 views of 350²):
#: the samples take four times the rows, so about four times the memory and three times the time
#: of pixel centres; beyond it a fit asks for them with ``pixel_samples=2``.
AUTO_MAX_PIXELS = 2_000_000


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
    averages, and (1, False) for linear HDR images, where the cost (about three times the run
    time) is not paid unless asked for, although antialiased HDR renders average pixels too; for
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
