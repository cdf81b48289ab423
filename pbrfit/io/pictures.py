"""Pictures of a fit that a person can read: a contact sheet per view (target | fit | |error|)
and ``maps.png`` (each fitted map, its standard error and, with the truth, the truth and the
error). Every panel is labelled and at least `MIN_PANEL` pixels on its short side (small images
are enlarged by whole factors, nearest neighbour, so a pixel stays a visible square); every false
colour is one perceptual map (`colormap`) on a scale a colour bar states with its units.

Drawn with Pillow (no plotting library to import: the pictures are written by every fit, and a
fit's wall time is a feature). Pillow's default font holds ASCII only, so the labels are ASCII.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ..physics.color import linear_to_srgb_host

__all__ = ["MIN_PANEL", "ERROR_PERCENTILE", "ERROR_FLOOR", "MAP_SCALE", "colormap", "enlarge", "error_scale",
           "display_peak", "contact_sheet", "maps_sheet"]

#: The least size of a panel's short side, in pixels of the picture.
MIN_PANEL = 256
#: The contact sheets' error scale is this percentile of |error| over every view's mask pixels ...
ERROR_PERCENTILE = 99.0
#: ... but at least this fraction of the mean target value over them (see `error_scale`).
ERROR_FLOOR = 0.02
#: The scale of maps.png's standard errors and errors against the truth, in the maps' own units
#: (every map lies in [0, 1]): a tenth of the whole range.
MAP_SCALE = 0.1
#: Matplotlib's "inferno" (S. van der Walt, N. Smith, 2015: perceptually uniform, monotonic in
#: lightness, readable in grey and by the colour blind) at 17 even steps, black to pale yellow;
#: linear interpolation between them stays within 7/255 of the full table.
_INFERNO = ("000004", "0b0724", "210c4a", "3d0965", "57106e", "71196e", "8a226a", "a32c61", "bc3754", "d24644",
            "e45a31", "f1731d", "f98e09", "fcac11", "f9cb35", "f2ea69", "fcffa4")
_INFERNO_RGB = np.array([[int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)] for h in _INFERNO], np.float32)
#: Where a false-colour panel has no value (outside the mask, a texel no view sees): mid grey,
#: a colour the colour map never takes.
NO_VALUE = (0.5, 0.5, 0.5)

_FONT_SIZE = 14
_PAD = 8          # between panels and around the picture
_LABEL = 20       # the band above a row of panels that holds their labels
_BAR = 16         # a colour bar's width
_BAR_TEXT = 80    # room right of a colour bar for its tick labels
_LINE = 18        # one line of notes under the panels


def colormap(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] (clipped; NaN as 0) to RGB in [0, 1] on `_INFERNO`, shape (..., 3)."""
    x = np.nan_to_num(np.clip(np.asarray(x, np.float32), 0.0, 1.0))
    t = x * (len(_INFERNO_RGB) - 1)
    i = np.minimum(t.astype(np.int64), len(_INFERNO_RGB) - 2)
    f = (t - i)[..., None]
    return _INFERNO_RGB[i] * (1 - f) + _INFERNO_RGB[i + 1] * f


def enlarge(image: np.ndarray, least: int = MIN_PANEL) -> np.ndarray:
    """`image` (H, W, C) enlarged by the least whole factor k with k min(H, W) >= `least`, each
    pixel repeated k x k times (nearest neighbour: pixels stay visible as pixels)."""
    k = max(1, math.ceil(least / max(1, min(image.shape[:2]))))
    return np.repeat(np.repeat(image, k, axis=0), k, axis=1)


def error_scale(targets: Sequence[np.ndarray], renders: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> float:
    """One |error| scale for every view of a fit: max(p, ERROR_FLOOR * m), where p is the
    `ERROR_PERCENTILE` th percentile of the per-pixel error (the mean over R, G, B of |fit - target|)
    over all views' mask pixels and m the mean target value over them.

    The percentile lets a fit's largest errors show their shape without a few outliers darkening
    the rest; one scale for all views lets views be compared. The floor keeps a fit exact to float
    rounding black instead of magnifying rounding noise into bright edges: an error under 2% of
    the signal is near the noise of a good photograph. Units: those of the images (display values
    for sRGB captures, linear radiance for EXR/HDR). 1.0 when no pixel is in any mask."""
    errors, values = [], []
    for target, fitted, mask in zip(targets, renders, masks):
        m = np.asarray(mask, bool)
        t, f = np.asarray(target, np.float64), np.asarray(fitted, np.float64)
        errors.append(np.abs(f - t).mean(-1)[m])
        values.append(t[m])
    errors = np.concatenate(errors) if errors else np.zeros(0)
    if errors.size == 0:
        return 1.0
    floor = ERROR_FLOOR * float(np.mean(np.concatenate(values)))
    scale = max(float(np.percentile(errors, ERROR_PERCENTILE)), floor)
    return scale if math.isfinite(scale) and scale > 0 else 1.0


def display_peak(targets: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> float:
    """The linear value shown as white in the contact sheets of a linear (EXR/HDR) capture, one for
    every view: the 99th percentile of the targets over all mask pixels (1.0 without any)."""
    values = [np.asarray(t)[np.asarray(m, bool)] for t, m in zip(targets, masks)]
    values = np.concatenate(values) if values else np.zeros(0)
    peak = float(np.percentile(values, 99)) if values.size else 1.0
    return peak if math.isfinite(peak) and peak > 0 else 1.0


def _font():
    try:
        return ImageFont.load_default(size=_FONT_SIZE)  # Pillow >= 10.1 with FreeType: scalable
    except (TypeError, OSError, ImportError):  # older Pillow, or no FreeType: the bitmap font
        return ImageFont.load_default()


def _rgb8(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    if x.ndim == 2:
        x = x[..., None]
    if x.shape[-1] == 1:
        x = np.repeat(x, 3, axis=-1)
    return np.round(np.clip(np.nan_to_num(x), 0.0, 1.0) * 255).astype(np.uint8)


def _ticks(scale: float) -> list[tuple[float, str]]:
    """(fraction of the bar, label) at 0, half and the whole scale; the top is '>=': brighter
    values are clipped to it."""
    return [(0.0, "0"), (0.5, f"{scale / 2:.3g}"), (1.0, f">= {scale:.3g}")]


def _colour_bar(image: Image.Image, x: int, y: int, height: int, scale: float, title: str, font) -> None:
    """A vertical bar of `colormap` from 0 (bottom) to `scale` (top) at (x, y), ticks labelled, its
    title above it."""
    ramp = np.repeat(colormap(np.linspace(1.0, 0.0, height))[:, None], _BAR, axis=1)
    image.paste(Image.fromarray(_rgb8(ramp)), (x, y))
    draw = ImageDraw.Draw(image)
    draw.rectangle([x, y, x + _BAR - 1, y + height - 1], outline="black")
    for frac, label in _ticks(scale):
        ty = y + round((1.0 - frac) * (height - 1))
        draw.line([(x + _BAR, ty), (x + _BAR + 3, ty)], fill="black")
        anchor = "lt" if frac == 1.0 else ("ld" if frac == 0.0 else "lm")  # inside the bar's height
        draw.text((x + _BAR + 5, ty), label, fill="black", font=font, anchor=anchor)
    draw.text((x, y - 4), title, fill="black", font=font, anchor="ld")


def _compose(rows: Sequence[Sequence[Optional[tuple[str, np.ndarray]]]], bar: tuple[float, str],
             notes: Sequence[str]) -> np.ndarray:
    """A grid of labelled panels (each cell (label, RGB in [0, 1]) or None for an empty cell, or
    (label, None) for a cell with only its label), a colour bar beside it (scale, title) and lines
    of notes under it; (H, W, 3) uint8."""
    panels = [[None if c is None or c[1] is None else _rgb8(enlarge(c[1])) for c in row] for row in rows]
    cell_h = max(p.shape[0] for row in panels for p in row if p is not None)
    cell_w = max(p.shape[1] for row in panels for p in row if p is not None)
    columns = max(len(row) for row in rows)
    font = _font()
    grid_w = _PAD + columns * (cell_w + _PAD)
    grid_h = len(rows) * (_LABEL + cell_h + _PAD)
    notes_w = max((round(font.getlength(n)) + 2 * _PAD for n in notes), default=0)
    width = max(grid_w + max(_BAR + _BAR_TEXT, round(font.getlength(bar[1]))) + _PAD, notes_w)
    height = _PAD + grid_h + len(notes) * _LINE + _PAD
    image = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(image)
    top = _PAD  # each row: a band with its labels (and, in the first, the bar's title), then its panels
    for r, row in enumerate(rows):
        y = top + r * (_LABEL + cell_h + _PAD)
        for c, cell in enumerate(row):
            if cell is None:
                continue
            x = _PAD + c * (cell_w + _PAD)
            draw.text((x, y + _LABEL - 4), cell[0], fill="black", font=font, anchor="ld")
            panel = panels[r][c]
            if panel is not None:
                image.paste(Image.fromarray(panel), (x + (cell_w - panel.shape[1]) // 2,
                                                     y + _LABEL + (cell_h - panel.shape[0]) // 2))
    _colour_bar(image, grid_w, top + _LABEL, grid_h - _LABEL - _PAD, bar[0], bar[1], font)
    for i, note in enumerate(notes):
        draw.text((_PAD, top + grid_h + i * _LINE), note, fill="black", font=font)
    return np.asarray(image)


def contact_sheet(target: np.ndarray, fitted: np.ndarray, mask: np.ndarray, is_srgb: bool, scale: float,
                  peak: float = 1.0, title: str = "") -> np.ndarray:
    """One view's sheet, (H, W, 3) uint8: target | fitted render | |error| in `colormap` on
    [0, `scale`] (`error_scale`: the same for every view of a fit), grey outside the mask, with the
    scale's colour bar and a note of its units. `target` and `fitted` are as the image file holds
    them (sRGB-encoded display values when `is_srgb`, else linear radiance, shown divided by
    `peak`, `display_peak`, and sRGB-encoded)."""
    t, f = np.asarray(target, np.float32), np.asarray(fitted, np.float32)
    m = np.asarray(mask, bool)
    err = np.abs(f.astype(np.float64) - t).mean(-1)
    heat = np.where(m[..., None], colormap(err / scale), np.asarray(NO_VALUE, np.float32))

    def shown(x):
        return np.clip(x, 0.0, 1.0) if is_srgb else linear_to_srgb_host(np.clip(x / peak, 0.0, 1.0))

    units = "display values (sRGB-encoded, 0 to 1)" if is_srgb else "linear radiance"
    lead = f"{title}: " if title else ""
    exposure = "" if is_srgb else f"; target and fit shown with {peak:.3g} as white"
    notes = [f"{lead}|error| = mean over R, G, B of |fit - target|, in {units}{exposure}",
             "one error scale for every view of this fit; grey: outside the mask (not fitted)"]
    bar = (scale, "|error|, display value" if is_srgb else "|error|, radiance")
    return _compose([[("target", shown(t)), ("fit", shown(f)), ("|fit - target|", heat)]], bar, notes)


def _seen(values: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """`values` (H, W) in `colormap` on [0, MAP_SCALE], grey where no view sees the texel."""
    seen = np.asarray(coverage) > 0
    ok = seen & np.isfinite(values)
    return np.where(ok[..., None], colormap(np.where(ok, values, 0.0) / MAP_SCALE), np.asarray(NO_VALUE, np.float32))


def maps_sheet(material, uncertainty: np.ndarray, coverage: np.ndarray, truth=None) -> np.ndarray:
    """``maps.png``, (H, W, 3) uint8: a row per map (base colour, metallic, roughness, and the
    normal when fitted); in each, the fitted map, its standard error (the largest of its channels',
    from `uncertainty`, the spec's five channels) and, with `truth` (a `Material` at the fitted
    resolution), the true map and |fit - truth| (the largest over channels). σ and error share one
    colour bar on [0, `MAP_SCALE`], so an error can be read against its σ; grey marks texels no
    view sees (coverage 0). Base colour is shown sRGB-encoded, the others as linear grey, the
    normal as its 8-bit encoding n/2 + 1/2; its error is the angle between the normals, in units
    of 90 degrees times `MAP_SCALE` (see the note)."""
    unc = np.asarray(uncertainty, np.float32)
    cov = np.asarray(coverage)
    cov = cov[..., 0] if cov.ndim == 3 else cov
    shape = tuple(np.asarray(material.base_color).shape[:2])
    if truth is not None:
        for name in ("base_color", "metallic", "roughness"):
            if tuple(np.asarray(getattr(truth, name)).shape[:2]) != shape:
                raise ValueError(f"maps_sheet: truth {name} is {np.asarray(getattr(truth, name)).shape[:2]}, "
                                 f"the fit {shape}: resample it first")
    rows = []
    for name, label, channels, show in (("base_color", "base colour", slice(0, 3), linear_to_srgb_host),
                                        ("metallic", "metallic", slice(3, 4), None),
                                        ("roughness", "roughness", slice(4, 5), None)):
        fit = np.asarray(getattr(material, name), np.float32)
        shown = (lambda x: show(np.clip(x, 0.0, 1.0))) if show else (lambda x: np.clip(x, 0.0, 1.0))
        sigma = unc[..., channels].max(-1)
        held = bool(np.all(sigma[cov > 0] == 0)) if np.any(cov > 0) else False
        row = [(f"{label}: fit", shown(fit)), (f"{label}: sigma" + (" (held: 0)" if held else ""), _seen(sigma, cov))]
        if truth is not None:
            t = np.asarray(getattr(truth, name), np.float32)
            row += [(f"{label}: truth", shown(t)), (f"{label}: |fit - truth|", _seen(np.abs(fit - t).max(-1), cov))]
        rows.append(row)
    notes = [f"sigma: one standard error (uncertainty.exr); sigma and |fit - truth| on one scale, 0 to {MAP_SCALE:g} "
             "in the maps' units (each map lies in 0 to 1)",
             "base colour: the largest of R, G, B; grey: texels no view sees (coverage 0, not fitted)"]
    normal = getattr(material, "normal", None)
    if normal is not None:
        n = np.asarray(normal, np.float32)
        row = [("normal: fit", n * 0.5 + 0.5), ("normal: sigma (its median: report.json)", None)]
        t = None if truth is None else getattr(truth, "normal", None)
        if t is not None and np.asarray(t).shape == n.shape:
            t = np.asarray(t, np.float32)
            degrees = np.degrees(np.arccos(np.clip((n * t).sum(-1), -1.0, 1.0)))
            ncov = cov if cov.shape == n.shape[:2] else np.ones(n.shape[:2])
            row += [("normal: truth", t * 0.5 + 0.5), ("normal: angle to truth", _seen(degrees / 90.0, ncov))]
            notes.append(f"normal: the angle to the truth on the same bar read as a fraction of 90 degrees "
                         f"(the top, {MAP_SCALE:g}, is {90 * MAP_SCALE:g} degrees)")
        rows.append(row)
    return _compose(rows, (MAP_SCALE, "sigma, |error|"), notes)
