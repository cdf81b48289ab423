"""Map resolution: the default map size a capture's views support, and the coarse-to-fine levels."""

from __future__ import annotations

import math

import numpy as np

from .observations import Observations, coverage_counts, observations_from_capture, texel_layout

__all__ = ["default_resolution", "schedule", "LEVEL_FACTOR", "PIXELS_PER_TEXEL", "OBSERVATIONS_PER_TEXEL",
           "MAX_RESOLUTION"]

#: Each coarse-to-fine level is this factor finer than the one before (see experiments/solvers.md).
LEVEL_FACTOR = 4
#: `default_resolution` picks the finest power of two whose texels are at least this many
#: pixels wide in the median view (below one pixel per texel, neighbours become inseparable).
PIXELS_PER_TEXEL = 1.0
#: ... and at which the observed texels get at least this many pixel observations each, over
#: all views (a texel has 5 unknowns; a pixel gives 3 numbers, and metallic and roughness need
#: several directions).
OBSERVATIONS_PER_TEXEL = 8.0
MAX_RESOLUTION = 2048


def _median_footprint(obs: Observations) -> float:
    """Median side (in uv units) of one pixel's footprint on the texture, over all views."""
    uv = np.asarray(obs.pixel_rows(obs.uv))  # one sample per pixel: the pixel grid's spacing
    vidx = np.asarray(obs.pixel_rows(obs.view_index))
    pix = np.asarray(obs.pixel_rows(obs.pixel))
    sides = []
    for view, (h, w) in enumerate(obs.shapes):
        sel = vidx == view
        img = np.full((h * w, 2), np.nan)
        img[pix[sel]] = uv[sel]
        img = img.reshape(h, w, 2)
        du = img[:-1, 1:] - img[:-1, :-1]
        dv = img[1:, :-1] - img[:-1, :-1]
        area = np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
        sides.append(np.sqrt(area[np.isfinite(area)]))
    sides = np.concatenate(sides) if sides else np.zeros(0)
    sides = sides[sides < 0.25]  # seams of the uv layout are not footprints
    return float(np.median(sides)) if sides.size else 1.0


def default_resolution(capture_or_obs) -> int:
    """The finest power-of-two map size whose texels are at least `PIXELS_PER_TEXEL` pixels
    wide, judged by the median pixel footprint in uv over all views, and whose observed texels
    get at least `OBSERVATIONS_PER_TEXEL` pixels each on average (more views allow finer maps).
    The map has no more texels than the views have pixels: views of a small part of the texture
    (close-ups, a narrow field of view) would otherwise ask for a fine map the solve pays for
    whole, almost all of it unseen (pass ``resolution`` for that)."""
    obs = capture_or_obs if isinstance(capture_or_obs, Observations) else observations_from_capture(capture_or_obs)
    side = _median_footprint(obs) * PIXELS_PER_TEXEL
    n = 2 ** int(math.floor(math.log2(max(1.0 / max(side, 1e-9), 1.0))))
    most = 2 ** int(math.floor(math.log2(max(math.sqrt(obs.num_pixels), 1.0))))
    n = int(min(max(n, 1), MAX_RESOLUTION, most))
    while n > 1:
        seen = int(np.sum(coverage_counts(texel_layout(obs, (n, n))) > 0))
        if obs.num_pixels >= OBSERVATIONS_PER_TEXEL * seen:
            break
        n //= 2
    return n


def schedule(resolution: tuple[int, int], factor: int = LEVEL_FACTOR) -> list[tuple[int, int]]:
    """Coarse-to-fine levels: a uniform material (1, 1), then sizes growing by `factor` up to
    `resolution` (each level divides the final size exactly)."""
    h, w = resolution
    levels = [(h, w)]
    while levels[-1][0] % factor == 0 and levels[-1][1] % factor == 0 and min(levels[-1]) // factor >= 4:
        levels.append((levels[-1][0] // factor, levels[-1][1] // factor))
    levels.append((1, 1))
    return list(dict.fromkeys(reversed(levels)))
