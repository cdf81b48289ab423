"""The fit output folder (capture spec, "The fit output"), written whole or not at all.

maps (EXR + PNG), ``uncertainty.exr``, ``coverage.exr``, ``material.glb``, ``report.json``, a
contact sheet per view (target | fitted render | |error|) under ``views/``, ``maps.png`` (the
maps, their σ and, with the truth, the truth and the error; `pbrfit.io.pictures`) and
``convergence.png``.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from .atomic import atomic_dir
from .gltf_export import write_gltf
from .material_files import write_material
from .images import write_image
from .pictures import contact_sheet, display_peak, error_scale, maps_sheet

__all__ = ["UNCERTAINTY_CHANNELS", "write_fit_output"]

#: Channel names of uncertainty.exr, in the spec's order (base R, G, B, metallic, roughness).
#: OpenEXR stores channels sorted by name and OpenImageIO reads R, G, B first and then the rest
#: by name, so these names come back in this order; layered names ("base_color.R") would not.
UNCERTAINTY_CHANNELS = ("R", "G", "B", "metallic", "roughness")


def _convergence_plot(path: Path, history: Sequence[dict], size: tuple[int, int] = (520, 320)) -> None:
    """Loss against step on a log axis, drawn with PIL (no plotting library to import: the plot is
    one of a fit's outputs, and a fit's wall time is a feature). Decade grid lines, labelled."""
    steps = np.asarray([h["step"] for h in history], np.float64)
    with np.errstate(invalid="ignore"):
        loss = np.log10(np.maximum(np.asarray([h["loss"] for h in history], np.float64), 1e-30))
    finite = np.isfinite(loss) & np.isfinite(steps)  # a NaN or inf loss is not drawn
    steps, loss = steps[finite], loss[finite]
    width, height = size
    left, right, top, bottom = 64, 16, 30, 40
    image = Image.new("RGB", size, "white")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default()
    lo, hi = (math.floor(loss.min()), math.ceil(loss.max())) if loss.size else (0, 1)
    hi = max(hi, lo + 1)
    s_max = max(float(steps.max()) if steps.size else 1.0, 1.0)

    def xy(step, value):
        return (left + (width - left - right) * step / s_max, top + (height - top - bottom) * (hi - value) / (hi - lo))

    every = max(1, math.ceil((hi - lo) / 8))  # at most about eight labelled decades
    for decade in range(lo, hi + 1):
        y = xy(0, decade)[1]
        draw.line([(left, y), (width - right, y)], fill=(225, 225, 225))
        if (decade - lo) % every == 0:
            draw.text((4, y - 6), f"1e{decade}", fill="black", font=font)
    tick = next((t * 10**k for k in range(6) for t in (1, 2, 5) if s_max / (t * 10**k) <= 8), 10**6)
    for step in range(0, int(s_max) + 1, tick):
        x = xy(step, lo)[0]
        draw.line([(x, height - bottom), (x, height - bottom + 4)], fill="black")
        draw.text((x - 4, height - bottom + 6), str(step), fill="black", font=font)
    draw.rectangle([left, top, width - right, height - bottom], outline="black")
    points = [xy(a, b) for a, b in zip(steps, loss)]
    if len(points) > 1:
        draw.line(points, fill=(31, 119, 180), width=2)
    for x, y in points:
        draw.ellipse([x - 2.5, y - 2.5, x + 2.5, y + 2.5], fill=(31, 119, 180))
    draw.text((left, 8), "convergence: objective 1/2 sum r^2 (data + prior), log scale", fill="black", font=font)
    draw.text(((width - left) // 2 + left - 12, height - 16), "step", fill="black", font=font)
    image.save(path)


def _json_safe(x):
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else (None if math.isnan(x) else ("inf" if x > 0 else "-inf"))
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.ndarray):
        return _json_safe(x.tolist())
    if isinstance(x, Path):
        return str(x)
    return x


def write_fit_output(
    out_dir: os.PathLike,
    capture,
    material,
    uncertainty: np.ndarray,
    coverage: np.ndarray,
    report: dict,
    targets: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    renders: Sequence[np.ndarray] = (),
    history: Sequence[dict] = (),
    write_normal: bool = False,
    truth=None,
) -> Path:
    """Write a fit's output folder at `out_dir` atomically (built under a temporary name).

    targets: per view (image as the file holds it, mask); renders: per view the fitted render in
    the same space. Both optional (no contact sheets without them). truth: the true `Material` at
    the fitted resolution, or None; with it ``maps.png`` shows the truth and the error too.
    """

    out_dir = Path(out_dir)
    uncertainty = np.asarray(uncertainty, np.float32)
    coverage = np.asarray(coverage, np.float32)
    if uncertainty.shape[-1] != len(UNCERTAINTY_CHANNELS):
        raise ValueError(f"uncertainty must have {len(UNCERTAINTY_CHANNELS)} channels, got {uncertainty.shape}")
    if not write_normal and getattr(material, "normal", None) is not None:
        material = type(material)(material.base_color, material.metallic, material.roughness)
    with atomic_dir(out_dir, kind="fit") as tmp:
        tmp = Path(tmp)
        write_material(tmp, material)
        write_image(tmp / "uncertainty.exr", uncertainty, "float", channel_names=UNCERTAINTY_CHANNELS)
        write_image(tmp / "coverage.exr", coverage[..., None] if coverage.ndim == 2 else coverage, "float")
        write_gltf(tmp / "material.glb", capture.mesh, material, capture.world_up)
        Image.fromarray(maps_sheet(material, uncertainty, coverage, truth)).save(tmp / "maps.png")
        if targets and renders:
            (tmp / "views").mkdir()
            masks = [mask for _, mask in targets]
            scale = error_scale([t for t, _ in targets], renders, masks)
            peak = display_peak([t for t, _ in targets], masks)
            for k, ((target, mask), fitted) in enumerate(zip(targets, renders)):
                is_srgb = capture.frames[k].color_space == "srgb"
                sheet = contact_sheet(target, fitted, mask, is_srgb, scale, peak, title=f"view {k:03d}")
                Image.fromarray(sheet).save(tmp / "views" / f"{k:03d}.png")
        if history:
            _convergence_plot(tmp / "convergence.png", history)
        (tmp / "report.json").write_text(json.dumps(_json_safe(report), indent=2) + "\n")
    return out_dir
