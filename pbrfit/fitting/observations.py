"""Observations: every usable pixel of every view as flat shading inputs, its target and the
texels it reads.

Geometry is fixed, so what a pixel sees (normal, view direction, incident light, uv) is computed
once and never differentiated. A pixel is *usable* when the mesh covers it, its mask is on and,
for LDR images, no channel sits at the file's maximum code (a clipped highlight says only
"at least this bright"). The fitted objective is the sum over usable pixels of the squared
difference between the image value and the rendered value *in the image's own space*: radiance
× 2^exposure, tone mapped, and sRGB-encoded for sRGB files (`pbrfit.physics.color.encode`).

Pixel footprints. A camera pixel integrates the radiance over its area; a renderer that
antialiases (supersampling, a reconstruction filter) writes that average, not the radiance at
the pixel's centre. With ``pixel_samples`` n > 1 each usable pixel becomes n × n *sample rows*
(`pixel_offsets`: the centres of an n × n grid of sub-pixels, a box filter, which is exactly an
n × n supersampled capture), consecutive in every per-pixel field (``samples`` = n², the pixel's
target repeated), and the objective compares the *mean linear radiance* of a pixel's samples with
its value (`pbrfit.fitting.objective`). A pixel is usable only where every sample hits the mesh.

A `TexelLayout` says which texels each pixel reads at one map resolution: the four bilinear
texels and weights of `pbrfit.physics.textures.bilinear_weights` (the exact sparsity of the problem),
or a single texel of weight 1 for a uniform material. The four are the corners of the 2 × 2 *cell*
of the map that the sample falls in, always in one order (`CELL_CORNERS`), so that the texels
a row reads follow from its first one and the map's shape (`pbrfit.fitting.objective.sample_texels`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Optional, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..errors import CaptureError
from .defaults import MAX_PIXEL_SAMPLES
from ..render.shade import ViewInputs
from ..render.views import capture_gbuffers, capture_views, view_rows
from ..scene.camera import pixel_offsets, sample_camera
from ..physics.textures import bilinear_weights
from ..transfer import to_device
from ..physics.color import inverse_tonemap, linear_to_srgb_host, srgb_to_linear

__all__ = ["Observations", "PIXEL_FIELDS", "TexelLayout", "CELL_CORNERS", "observations_from_views",
           "observations_from_capture", "row_geometry", "MAX_PIXEL_SAMPLES", "texel_layout", "uniform_layout",
           "layout_for", "coverage_counts", "neighbour_pairs", "inverted_targets", "linear_radiance"]


#: The per-pixel fields of `Observations` (leading axis: rows, P × samples).
PIXEL_FIELDS = ("normal", "tangent", "view", "light_l", "light_radiance", "uv", "exposure", "target",
                "residual_weight", "view_index", "pixel")


class Observations(eqx.Module):
    """Usable pixels of all views, concatenated (P pixels, L lights; views with fewer lights are
    padded with lights of zero radiance). Every per-pixel field has one row per pixel sample:
    R = P × ``samples`` rows, a pixel's samples consecutive (module docstring); with
    ``samples`` = 1 (the default) a row is a pixel, shaded at its centre.

    Attributes:
        normal, view: (P, 3) unit shading normal and surface-to-camera direction.
        tangent: (P, 4) unit tangent and handedness (for normal maps).
        light_l, light_radiance: (P, L, 3) per light: direction to it and arriving radiance.
        uv: (P, 2) texture coordinates (glTF orientation).
        exposure: (P,) exposure in EV of the pixel's frame.
        target: (P, 3) the image's values (linear, or sRGB-encoded display values when
            ``color_space == "srgb"``, i.e. the space residuals are taken in).
        residual_weight: (P, 3) the factor on each value's residual: σ_ref / σ_p for a noise level
            σ_p that depends on the value (`pbrfit.fitting.noise`), 1 where the noise is uniform (the
            default: plain least squares).
        view_index: (P,) which view each pixel belongs to.
        pixel: (P,) flat pixel index in its view.
        shapes: (H, W) of each view (static).
        tonemap, color_space: how radiance becomes image values (static).
        samples: rows per pixel (static).
    """

    normal: Float[Array, "P 3"]
    tangent: Float[Array, "P 4"]
    view: Float[Array, "P 3"]
    light_l: Float[Array, "P L 3"]
    light_radiance: Float[Array, "P L 3"]
    uv: Float[Array, "P 2"]
    exposure: Float[Array, " P"]
    target: Float[Array, "P 3"]
    residual_weight: Float[Array, "P 3"]
    view_index: Int[Array, " P"]
    pixel: Int[Array, " P"]
    shapes: tuple = eqx.field(static=True)
    tonemap: str = eqx.field(static=True, default="none")
    color_space: str = eqx.field(static=True, default="linear")
    samples: int = eqx.field(static=True, default=1)

    @property
    def num_rows(self) -> int:
        """Rows of the per-pixel fields: pixels × samples."""
        return int(self.target.shape[0])

    @property
    def num_pixels(self) -> int:
        return self.num_rows // self.samples

    def pixel_rows(self, a):
        """The first sample's row of each pixel of a per-row array (P, ...)."""
        return a[:: self.samples]

    @property
    def num_views(self) -> int:
        return len(self.shapes)

    def select_views(self, keep: Sequence[int]) -> "Observations":
        """The observations of some views only (numbering of `view_index` kept)."""
        sel = np.isin(np.asarray(self.view_index), np.asarray(list(keep)))
        return _take(self, np.flatnonzero(sel))


def _take(obs: Observations, rows: np.ndarray) -> Observations:
    rows = jnp.asarray(rows, jnp.int32)
    return eqx.tree_at(
        lambda o: tuple(getattr(o, n) for n in PIXEL_FIELDS),
        obs,
        tuple(getattr(obs, n)[rows] for n in PIXEL_FIELDS),
    )


class TexelLayout(eqx.Module):
    """Which texels each pixel reads: (P, 4) flat texel indices and weights; `shape` (H, W) of
    the maps (``(1, 1)`` for a uniform material)."""

    index: Int[Array, "P 4"]
    weight: Float[Array, "P 4"]
    shape: tuple = eqx.field(static=True)

    @property
    def num_texels(self) -> int:
        return int(self.shape[0] * self.shape[1])


def _pad_lights(a: np.ndarray, lights: int, fill: np.ndarray) -> np.ndarray:
    extra = lights - a.shape[1]
    if extra == 0:
        return a
    pad = np.broadcast_to(fill, (a.shape[0], extra, 3))
    return np.concatenate([a, pad], axis=1)


def observations_from_views(
    views: Sequence[ViewInputs],
    images: Sequence[np.ndarray],
    exposures: Optional[Sequence[float]] = None,
    usable: Optional[Sequence[Optional[np.ndarray]]] = None,
    tonemap: str = "none",
    color_space: str = "linear",
) -> Observations:
    """Observations from per-view `ViewInputs` and the (H, W, 3) images they were taken with.

    `images` hold the file's values (display values for sRGB: what `encode` produces).
    `usable` are optional (H, W) bool masks of pixels to keep (e.g. not saturated).
    """
    exposures = [0.0] * len(views) if exposures is None else list(exposures)
    usable = [None] * len(views) if usable is None else list(usable)
    lights = max((int(v.light_l.shape[1]) for v in views), default=0)
    parts = {k: [] for k in PIXEL_FIELDS}
    for k, (vi, img, ev, use) in enumerate(zip(views, images, exposures, usable)):
        pix = np.asarray(vi.pixel)
        keep = np.ones(pix.shape[0], bool)
        if use is not None:
            keep = np.asarray(use, bool).reshape(-1)[pix]
        img = np.asarray(img, np.float32).reshape(-1, np.asarray(img).shape[-1])[:, :3]
        keep &= np.all(np.isfinite(img[pix]), axis=-1)
        rows = np.flatnonzero(keep)
        normal = np.asarray(vi.normal)[rows]
        parts["normal"].append(normal)
        parts["tangent"].append(np.asarray(vi.tangent)[rows])
        parts["view"].append(np.asarray(vi.view)[rows])
        parts["light_l"].append(_pad_lights(np.asarray(vi.light_l)[rows], lights, np.array([0.0, 0.0, 1.0])))
        parts["light_radiance"].append(_pad_lights(np.asarray(vi.light_radiance)[rows], lights, np.zeros(3)))
        parts["uv"].append(np.asarray(vi.uv)[rows])
        parts["exposure"].append(np.full(rows.shape[0], ev, np.float32))
        parts["target"].append(img[pix[rows]])
        parts["residual_weight"].append(np.ones((rows.shape[0], 3), np.float32))
        parts["view_index"].append(np.full(rows.shape[0], k, np.int32))
        parts["pixel"].append(pix[rows].astype(np.int32))
    cat = {k: np.concatenate(v, axis=0) for k, v in parts.items()}
    if lights == 0:
        cat["light_l"] = np.zeros((cat["normal"].shape[0], 0, 3), np.float32)
        cat["light_radiance"] = np.zeros((cat["normal"].shape[0], 0, 3), np.float32)
    return Observations(
        **{k: to_device(v, np.float32 if v.dtype.kind == "f" else None) for k, v in cat.items()},
        shapes=tuple(tuple(int(s) for s in v.shape) for v in views),
        tonemap=tonemap,
        color_space=color_space,
    )


def _sample_views(capture, cache_dir, n: int) -> list:
    """Per frame, the `ViewInputs` of each of the n × n samples (`pixel_offsets`), kept to the
    pixels that every sample sees (each sample's silhouettes and masks applied)."""
    per_sample = []
    for offset in pixel_offsets(n):
        shifted = dataclasses.replace(capture, frames=[dataclasses.replace(f, camera=sample_camera(f.camera, offset))
                                                       for f in capture.frames])
        per_sample.append(capture_views(shifted, capture_gbuffers(shifted, cache_dir)))
    out = []
    for k in range(len(capture.frames)):
        common = functools.reduce(np.intersect1d, [np.asarray(v[k].pixel) for v in per_sample])
        out.append([view_rows(v[k], common) for v in per_sample])
    return out


def _interleave(parts: Sequence[Observations]) -> Observations:
    """Sample observations of the same pixels (same order) as consecutive rows of one."""
    n = len(parts)
    fields = {}
    for name in PIXEL_FIELDS:
        a = np.stack([np.asarray(getattr(o, name)) for o in parts], axis=1)
        fields[name] = to_device(a.reshape((a.shape[0] * n,) + a.shape[2:]))  # (no -1: L may be 0)
    return dataclasses.replace(parts[0], samples=n, **fields)


def observations_from_capture(capture, cache_dir=None, views=None, pixel_samples: int = 1) -> Observations:
    """Ray-cast every frame of a `pbrfit.scene.capture.Capture` once and gather its usable pixels.

    Masked pixels, pixels the mesh misses and saturated LDR pixels (`Frame.saturated`) are left
    out. `views` may pass precomputed `ViewInputs` (one per frame) to skip the ray casting.
    A capture that leaves no usable pixel, or whose pixels no light reaches (no environment,
    every punctual light off or pointing away), is `CaptureError`: nothing could be fitted; so
    is a NaN or inf pixel on the mesh (`pbrfit.scene.capture.Frame.nonfinite`).

    `pixel_samples` n > 1 ray-casts each frame n × n times, at the `pixel_offsets` (module
    docstring: pixel footprints), and keeps the pixels every sample sees.
    """
    n = int(pixel_samples)
    if n != pixel_samples or not 1 <= n <= MAX_PIXEL_SAMPLES:
        raise ValueError(f"pixel_samples must be an integer from 1 to {MAX_PIXEL_SAMPLES}, got {pixel_samples!r}")
    if views is not None and (isinstance(views, (str, bytes)) or not hasattr(views, "__len__")
                              or len(views) != len(capture.frames)
                              or not all(isinstance(v, ViewInputs) for v in views)):
        raise ValueError(f"views: expected one pbrfit.render.shade.ViewInputs per frame ({len(capture.frames)}), "
                         f"got {views!r:.80}")
    if n > 1:
        if views is not None:
            raise ValueError("precomputed views hold pixel centres only: pass views=None with pixel_samples > 1")
        per_frame = _sample_views(capture, cache_dir, n)
        return _interleave([observations_from_capture(capture, views=[v[s] for v in per_frame])
                            for s in range(n * n)])
    color_space = getattr(capture, "color_space", "linear")
    if views is None:
        views = capture_views(capture, capture_gbuffers(capture, cache_dir))
    images, usable, exposures = [], [], []
    for frame in capture.frames:
        img = np.asarray(frame.image, np.float32)
        if color_space == "srgb":
            # frames hold decoded linear values; residuals live in file space
            img = linear_to_srgb_host(np.clip(img, 0.0, None))
        images.append(img)
        sat = getattr(frame, "saturated", None)
        usable.append(None if sat is None else ~np.asarray(sat, bool))
        exposures.append(float(getattr(frame, "exposure", 0.0)))
    name = getattr(capture, "json_path", None) or getattr(capture, "root", "capture")
    for k, (frame, view) in enumerate(zip(capture.frames, views)):
        bad = getattr(frame, "nonfinite", None)
        if bad is not None and bad.any():
            hit = np.asarray(bad).reshape(-1)[np.asarray(view.pixel)]
            if hit.any():
                flat = int(np.asarray(view.pixel)[np.flatnonzero(hit)[0]])
                width = np.asarray(bad).shape[1]
                raise CaptureError(
                    f"{name}: frames[{k}].file_path: {int(hit.sum())} pixel(s) on the mesh with NaN or inf values in "
                    f"{frame.file_path} (first at row {flat // width}, column {flat % width}); mask them out "
                    "(mask_path, or alpha 0) to use this frame"
                )
    obs = observations_from_views(views, images, exposures, usable, getattr(capture, "tonemap", "none"), color_space)
    if obs.num_pixels == 0:
        raise CaptureError(
            f"{name}: no usable pixels: in every frame each pixel is masked out, saturated or misses the mesh"
        )
    if getattr(capture, "environment", None) is None and not np.max(np.asarray(obs.light_radiance), initial=0.0) > 0.0:
        raise CaptureError(f"{name}: no light reaches the mesh: no environment, and every light is off or points away")
    return obs


def row_geometry(capture, obs: Observations, cache_dir=None) -> tuple[np.ndarray, np.ndarray]:
    """(R, 3) float64 surface points and (R, 3) float32 geometric normals (facing the camera) of
    the rows of `obs`, made from ``capture`` by `observations_from_capture` with the same
    ``cache_dir``: read from the frames' G-buffers (cached there, else cast again), a row's
    sample camera found from its place among its pixel's rows (`pixel_offsets`)."""
    n = math.isqrt(obs.samples)
    view_index, pixel = np.asarray(obs.view_index), np.asarray(obs.pixel)
    sample = np.arange(obs.num_rows) % obs.samples
    points = np.zeros((obs.num_rows, 3))
    normals = np.zeros((obs.num_rows, 3), np.float32)
    for s, offset in enumerate(pixel_offsets(n) if n > 1 else [None]):
        frames = capture.frames if offset is None else [dataclasses.replace(f, camera=sample_camera(f.camera, offset))
                                                        for f in capture.frames]
        for k, g in enumerate(capture_gbuffers(dataclasses.replace(capture, frames=frames), cache_dir)):
            rows = np.flatnonzero((view_index == k) & (sample == s))
            if len(rows):
                points[rows] = g.position.reshape(-1, 3)[pixel[rows]]
                normals[rows] = g.geometric_normal.reshape(-1, 3)[pixel[rows]]
    return points, normals


#: The (di, dj) of a cell's corners from its first texel, in the order of a row's four taps (a
#: bilinear sample's: `pbrfit.physics.textures.bilinear_weights`).
CELL_CORNERS = ((0, 0), (0, 1), (1, 0), (1, 1))


@functools.partial(jax.jit, static_argnames="shape")
def _as_cells(index, weight, shape: tuple[int, int]):
    """Bilinear taps as the corners of their cell, in `CELL_CORNERS` order, wrapped: a clamped
    sample at an edge reads one row (or column) twice, and its weights there add up on the cell's
    first row, the second getting weight 0 (elsewhere, and on a repeated map, the taps are the
    corners already)."""
    h, w = shape
    row, col = index // w, index % w
    second = 2 * (jnp.mod(row - row[:, :1], h) != 0) + (jnp.mod(col - col[:, :1], w) != 0)
    merged = jnp.sum(weight[..., None] * (second[..., None] == jnp.arange(4)), axis=1)
    corners = [jnp.mod(row[:, 0] + di, h) * w + jnp.mod(col[:, 0] + dj, w) for di, dj in CELL_CORNERS]
    return jnp.stack(corners, axis=1), merged


def texel_layout(obs: Observations, shape: tuple[int, int], wrap: str = "repeat") -> TexelLayout:
    """The four bilinear texels (and weights) each pixel (sample row) reads from (H, W) maps: the
    corners of its cell, in `CELL_CORNERS` order."""
    shape = tuple(int(s) for s in shape)
    index, weight = bilinear_weights(obs.uv, shape, wrap)
    index, weight = _as_cells(index.astype(jnp.int32), weight.astype(jnp.float32), shape)
    return TexelLayout(index, weight, shape)


def uniform_layout(obs: Observations) -> TexelLayout:
    """Every pixel reads the one texel of a uniform material (all four corners of the 1 × 1
    map's cell)."""
    p = obs.num_rows
    index = jnp.zeros((p, 4), jnp.int32)
    weight = jnp.zeros((p, 4), jnp.float32).at[:, 0].set(1.0)
    return TexelLayout(index, weight, (1, 1))


def layout_for(obs: Observations, shape: tuple[int, int], wrap: str = "repeat") -> TexelLayout:
    """`uniform_layout` for a (1, 1) map, else `texel_layout`."""
    return uniform_layout(obs) if tuple(shape) == (1, 1) else texel_layout(obs, shape, wrap)


def coverage_counts(layout: TexelLayout, samples: int = 1) -> np.ndarray:
    """(H, W) int32: how many pixel observations read each texel with nonzero weight. With
    `samples` rows per pixel, a pixel counts once per texel any of its samples reads."""
    idx = np.asarray(layout.index).reshape(-1)
    w = np.asarray(layout.weight).reshape(-1)
    if samples > 1:  # distinct (pixel, texel) pairs
        pixel = np.arange(idx.size) // (layout.index.shape[-1] * samples)
        pairs = np.unique(pixel[w > 0].astype(np.int64) * layout.num_texels + idx[w > 0])
        idx, w = pairs % layout.num_texels, np.ones(pairs.size)
    counts = np.bincount(idx[w > 0], minlength=layout.num_texels)
    return counts.astype(np.int32).reshape(layout.shape)


def neighbour_pairs(shape: tuple[int, int]) -> np.ndarray:
    """(E, 2) flat indices of 4-connected texel neighbours (no wrap), for the smoothness prior."""
    h, w = shape
    ids = np.arange(h * w).reshape(h, w)
    right = np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], -1)
    down = np.stack([ids[:-1, :].ravel(), ids[1:, :].ravel()], -1)
    return np.concatenate([right, down], 0).astype(np.int32)


def inverted_targets(obs: Observations) -> Float[Array, "R 3"]:
    """The rows' image values as the tone map's input: sRGB decoded, the tone map inverted
    (`pbrfit.physics.color.inverse_tonemap`)."""
    y = srgb_to_linear(obs.target) if obs.color_space == "srgb" else obs.target
    return inverse_tonemap(y, obs.tonemap)


def linear_radiance(obs: Observations, inverted: Optional[Array] = None) -> Float[Array, "R 3"]:
    """The radiance each row of ``obs`` saw: `inverted_targets` (or ``inverted``, already
    computed) with the exposure divided out."""
    inverted = inverted_targets(obs) if inverted is None else inverted
    return inverted * jnp.exp2(-obs.exposure)[:, None]
