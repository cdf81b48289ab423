"""The fit output folder (capture spec, "The fit output"), written whole or not at all.

maps (EXR + PNG), ``uncertainty.exr``, ``coverage.exr``, ``material.glb``, ``report.json``, a
contact sheet per view (target | fitted render | error heat map) under ``views/`` and
``convergence.png``.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["UNCERTAINTY_CHANNELS", "contact_sheet", "write_fit_output"]

#: Channel names of uncertainty.exr, in the spec's order (base R, G, B, metallic, roughness).
#: OpenEXR stores channels sorted by name and OpenImageIO reads R, G, B first and then the rest
#: by name, so these names come back in this order; layered names ("base_color.R") would not.
UNCERTAINTY_CHANNELS = ("R", "G", "B", "metallic", "roughness")


def _heat(err: np.ndarray, scale: float) -> np.ndarray:
    """Map |error| in [0, scale] to a black-red-yellow-white ramp."""
    x = np.clip(err / max(scale, 1e-12), 0.0, 1.0)
    return np.stack([np.clip(3 * x, 0, 1), np.clip(3 * x - 1, 0, 1), np.clip(3 * x - 2, 0, 1)], -1)


def _display(x: np.ndarray, is_srgb: bool) -> np.ndarray:
    """Values to show in an 8-bit PNG: sRGB-encoded, clipped."""
    from .color import linear_to_srgb

    x = np.clip(np.asarray(x, np.float32), 0.0, 1.0)
    return x if is_srgb else np.asarray(linear_to_srgb(x))


def contact_sheet(target: np.ndarray, fitted: np.ndarray, mask: np.ndarray, is_srgb: bool) -> np.ndarray:
    """(H, 3W, 3) image: target | fitted render | |error| heat map (white = the 99th percentile)."""
    err = np.abs(np.asarray(fitted, np.float64) - np.asarray(target, np.float64)).mean(-1)
    err = np.where(mask, err, 0.0)
    scale = float(np.percentile(err[mask], 99)) if np.any(mask) else 1.0
    if not is_srgb:
        peak = float(np.percentile(np.asarray(target)[mask], 99)) if np.any(mask) else 1.0
        target = np.asarray(target) / max(peak, 1e-6)
        fitted = np.asarray(fitted) / max(peak, 1e-6)
    return np.concatenate([_display(target, is_srgb), _display(fitted, is_srgb), _heat(err, scale)], axis=1)


def _convergence_plot(path: Path, history: Sequence[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["step"] for h in history]
    loss = [h["loss"] for h in history]
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
    ax.semilogy(steps, np.maximum(loss, 1e-30), marker="o", ms=3)
    ax.set_xlabel("step")
    ax.set_ylabel("loss (mean squared residual)")
    ax.set_title("convergence")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


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
) -> Path:
    """Write a fit's output folder at `out_dir` atomically (built under a temporary name).

    targets: per view (image as the file holds it, mask); renders: per view the fitted render in
    the same space. Both optional (no contact sheets without them).
    """
    from .io import atomic_dir, write_gltf, write_image, write_material

    out_dir = Path(out_dir)
    uncertainty = np.asarray(uncertainty, np.float32)
    coverage = np.asarray(coverage, np.float32)
    if uncertainty.shape[-1] != len(UNCERTAINTY_CHANNELS):
        raise ValueError(f"uncertainty must have {len(UNCERTAINTY_CHANNELS)} channels, got {uncertainty.shape}")
    if not write_normal and getattr(material, "normal", None) is not None:
        material = type(material)(material.base_color, material.metallic, material.roughness)
    with atomic_dir(out_dir, marker="report.json", what="pbrfit fit output") as tmp:
        tmp = Path(tmp)
        write_material(tmp, material)
        write_image(tmp / "uncertainty.exr", uncertainty, "float", channel_names=UNCERTAINTY_CHANNELS)
        write_image(tmp / "coverage.exr", coverage[..., None] if coverage.ndim == 2 else coverage, "float")
        write_gltf(tmp / "material.glb", capture.mesh, material)
        if targets and renders:
            (tmp / "views").mkdir()
            for k, ((target, mask), fitted) in enumerate(zip(targets, renders)):
                is_srgb = capture.frames[k].color_space == "srgb"
                sheet = contact_sheet(target, fitted, mask, is_srgb)
                write_image(tmp / "views" / f"{k:03d}.png", sheet.astype(np.float32), "uint8")
        if history:
            _convergence_plot(tmp / "convergence.png", history)
        (tmp / "report.json").write_text(json.dumps(_json_safe(report), indent=2) + "\n")
    return out_dir
