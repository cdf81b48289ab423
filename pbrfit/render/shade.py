"""Rendering: shade a view's G-buffer with a material, its lights and the environment.

Geometry is known and fixed, so `prepare_view` turns a G-buffer into flat per-pixel inputs once
(which pixels see the mesh, their uv, normal, tangent, view direction, and per light the
incident direction and the radiance that arrives, shadows included). Shading those inputs
(`shade`) is elementwise and differentiable; `render_view` adds texture sampling, normal
mapping, exposure, tone mapping and encoding, and scatters the pixels back into an image.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..physics import brdf
from ..physics.color import encode
from ..physics.material import Material, apply_normal_map, material_at
from ..physics.model import Model
from ..transfer import to_device
from ..physics.lights import incident
from ..lighting.pixel_ibl import interpolate_lobes, per_row, pixel_dfg, shade_pixel_ibl
from ..lighting.brdf_lut import lookup_brdf_lut
from ..lighting.ibl import OccludedTables, shade_ibl

__all__ = [
    "ViewInputs",
    "prepare_view",
    "light_arrays",
    "shade_punctual",
    "shade",
    "radiance_view",
    "shading_inputs",
    "render_view",
    "RENDER_CHUNK",
    "RENDER_MIN_ROWS",
    "render_rows",
]

#: Pixels shaded per compiled call in `render_view`: bounds memory for large views (the IBL and
#: Monte Carlo paths hold per-pixel sample arrays) while keeping one compilation per chunk size.
RENDER_CHUNK = 65536
#: A view of one chunk is padded to the next of 2^k and 1.5 · 2^k rows, at least these: the views of
#: a capture, whose hit counts all differ, share a compile or two (`render_rows`).
RENDER_MIN_ROWS = 256


class ViewInputs(eqx.Module):
    """Flat per-pixel shading inputs of one view, for the pixels where the mesh is hit.

    Attributes:
        pixel: (P,) flat index row * W + col of each shaded pixel.
        shape: (H, W) of the view (static).
        uv: (P, 2) texture coordinates (glTF orientation).
        normal: (P, 3) unit shading normal.
        tangent: (P, 4) unit tangent and handedness.
        view: (P, 3) unit direction from the surface to the camera.
        light_l: (P, L, 3) unit direction from the surface to each light.
        light_radiance: (P, L, 3) radiance arriving from each light (irradiance at normal
            incidence: color · intensity · window / d² · cone falloff · visibility).
    """

    pixel: Int[Array, " P"]
    uv: Float[Array, "P 2"]
    normal: Float[Array, "P 3"]
    tangent: Float[Array, "P 4"]
    view: Float[Array, "P 3"]
    light_l: Float[Array, "P L 3"]
    light_radiance: Float[Array, "P L 3"]
    shape: tuple[int, int] = eqx.field(static=True)

    @property
    def num_pixels(self) -> int:
        return int(self.pixel.shape[0])


def light_arrays(lights, points: np.ndarray, visibility: Optional[np.ndarray] = None):
    """Per point and light: unit direction to the light (P, L, 3) and arriving radiance (P, L, 3)."""
    # host points (a G-buffer) go over by `to_device`: jnp.asarray would compile a kernel per shape
    points = jnp.asarray(points, jnp.float32) if isinstance(points, jax.Array) else to_device(points, np.float32)
    if len(lights) == 0:
        empty = to_device(np.zeros((points.shape[0], 0, 3), np.float32))
        return empty, empty
    return _light_arrays(tuple(lights), points, visibility)


@eqx.filter_jit  # eagerly: one compile per image size and light set, not one per operation
def _light_arrays(lights, points, visibility):
    dirs, rad = zip(*(incident(light, points) for light in lights))
    light_l = jnp.stack(dirs, axis=1)
    light_radiance = jnp.stack(rad, axis=1)
    if visibility is not None:
        light_radiance = light_radiance * jnp.asarray(visibility, jnp.float32)[..., None]
    return light_l, light_radiance


def prepare_view(gbuffer, lights, mask: Optional[np.ndarray] = None) -> ViewInputs:
    """Flatten a G-buffer's hit pixels (and `mask`, if given) into `ViewInputs` for `lights`.

    The light arrays are computed over the whole (H, W) image and then gathered, so their
    (eager) jnp operations see the same shape for every view of a size and compile once, not
    once per pixel count.
    """
    keep = np.asarray(gbuffer.hit, bool)
    if mask is not None:
        keep = keep & np.asarray(mask, bool)
    height, width = keep.shape
    flat = np.flatnonzero(keep.reshape(-1))

    def whole(a):
        a = np.asarray(a)
        return a.reshape(height * width, *a.shape[2:])

    vis = whole(gbuffer.visibility) if len(lights) else None
    light_l, light_radiance = (np.asarray(a)[flat] for a in light_arrays(lights, whole(gbuffer.position), vis))
    return ViewInputs(
        pixel=to_device(flat, np.int32),
        uv=to_device(whole(gbuffer.uv)[flat], np.float32),
        normal=to_device(whole(gbuffer.normal)[flat], np.float32),
        tangent=to_device(whole(gbuffer.tangent)[flat], np.float32),
        view=to_device(whole(gbuffer.view)[flat], np.float32),
        light_l=to_device(light_l, np.float32),
        light_radiance=to_device(light_radiance, np.float32),
        shape=(height, width),
    )


@functools.partial(jax.jit, static_argnames="model")
def shade_punctual(
    normal: Float[Array, "P 3"],
    view: Float[Array, "P 3"],
    light_l: Float[Array, "P L 3"],
    light_radiance: Float[Array, "P L 3"],
    base_color: Float[Array, "P 3"],
    metallic: Float[Array, "P 1"],
    roughness: Float[Array, "P 1"],
    model: Model = Model(),
    dfg: Optional[Float[Array, "P 2"]] = None,
) -> Float[Array, "P 3"]:
    """Outgoing radiance from punctual lights: Σ_lights f(v, l) (n·l) E_light."""
    if light_l.shape[-2] == 0:
        return jnp.zeros_like(base_color)
    n_dot_v = jnp.sum(normal * view, axis=-1)[..., None]  # (P, 1) against (P, L)
    n_dot_l = jnp.sum(normal[:, None, :] * light_l, axis=-1)
    n_dot_h, v_dot_h = brdf.half_vector_cosines(n_dot_v, n_dot_l, None, brdf.v_plus_l_sq(view[:, None, :], light_l))
    f = brdf.evaluate_cosines(
        n_dot_v,
        n_dot_l,
        n_dot_h,
        v_dot_h,
        base_color[:, None, :],
        metallic[:, None, :],
        roughness[:, None, :],
        model,
        None if dfg is None else dfg[:, None, :],
        brdf.half_vector_sin2(normal[:, None, :], view[:, None, :], light_l),
    )
    return jnp.sum(f * light_radiance, axis=1)


@functools.partial(jax.jit, static_argnames="model")
def shade(
    normal: Float[Array, "P 3"],
    view: Float[Array, "P 3"],
    light_l: Float[Array, "P L 3"],
    light_radiance: Float[Array, "P L 3"],
    base_color: Float[Array, "P 3"],
    metallic: Float[Array, "P 1"],
    roughness: Float[Array, "P 1"],
    model: Model = Model(),
    ibl=None,
    occlusion: Optional[Float[Array, "P 1"]] = None,
    emissive: Optional[Float[Array, "P 3"]] = None,
) -> Float[Array, "P 3"]:
    """Linear outgoing radiance at each point: punctual lights + environment + emission.

    `ibl` is an `pbrfit.lighting.ibl.IBLTables` when ``model.ibl == "split_sum"`` (or with
    ``model.multiscatter``, for the DFG LUT), or the points' `pbrfit.lighting.pixel_ibl.PixelIBL` (one row
    per point) when ``model.ibl == "per_pixel"``; for the split sum it may be
    `pbrfit.lighting.ibl.OccludedTables` (one row of occlusion factors per point). Occlusion scales
    indirect (environment) light only. The Monte Carlo integrator is not a shading mode here: it
    is the reference `pbrfit.lighting.montecarlo.monte_carlo_radiance`.
    """
    factors = None
    if isinstance(ibl, OccludedTables):
        ibl, factors = ibl.tables, ibl.table
    dfg = None
    if model.multiscatter:
        if ibl is None:
            raise ValueError("Model(multiscatter=True) needs IBL tables (for the DFG LUT)")
        if model.ibl == "per_pixel":
            dfg = pixel_dfg(ibl, interpolate_lobes(ibl.table, roughness[..., 0]))
        else:
            n_dot_v = jnp.clip(jnp.sum(normal * view, axis=-1), 0.0, 1.0)
            dfg = lookup_brdf_lut(ibl.lut, n_dot_v, roughness[..., 0])
    out = shade_punctual(normal, view, light_l, light_radiance, base_color, metallic, roughness, model, dfg)
    if model.ibl == "split_sum":
        if ibl is None:
            raise ValueError("Model(ibl='split_sum') needs IBL tables; build them with pbrfit.lighting.ibl.build_ibl")

        out = out + shade_ibl(ibl, normal, view, base_color, metallic, roughness, model, occlusion, factors)
    elif model.ibl == "per_pixel":
        if ibl is None:
            raise ValueError("Model(ibl='per_pixel') needs the points' lobe integrals; "
                             "build them with pbrfit.lighting.pixel_ibl.pixel_ibl")

        env = shade_pixel_ibl(ibl, base_color, metallic, roughness, model)
        out = out + (env if occlusion is None else env * occlusion)
    elif model.ibl == "monte_carlo":
        raise ValueError("Model(ibl='monte_carlo') is the reference integrator: use pbrfit.lighting.montecarlo.monte_carlo_radiance")
    if emissive is not None:
        out = out + emissive
    return out


def shading_inputs(view: ViewInputs, material: Material, wrap: str = "repeat", normal_convention: str = "opengl"):
    """What a view's pixels shade with: (normal, base_color, metallic, roughness, occlusion,
    emissive), the material sampled at their uv (channels clipped to [0, 1], with the derivative
    from inside at 0 and 1: `brdf.clamp_inward`) and its normal map, if any, applied. occlusion
    and emissive are None when the material has none."""
    sample = material_at(material, view.uv, wrap)
    normal = view.normal
    if sample.normal is not None:
        normal = apply_normal_map(normal, view.tangent, sample.normal, normal_convention)
    unit = lambda x: brdf.clamp_inward(x, 0.0, 1.0)  # noqa: E731
    return (normal, unit(sample.base_color), unit(sample.metallic), unit(sample.roughness), sample.occlusion,
            sample.emissive)


def _radiance_chunk(view: ViewInputs, material: Material, model: Model, ibl, wrap: str, normal_convention: str):
    normal, base_color, metallic, roughness, occlusion, emissive = shading_inputs(view, material, wrap,
                                                                                  normal_convention)
    return shade(normal, view.view, view.light_l, view.light_radiance, base_color, metallic, roughness, model, ibl,
                 occlusion, emissive)


_radiance_chunk_jit = jax.jit(_radiance_chunk, static_argnames=("model", "wrap", "normal_convention"))


def _slice(view: ViewInputs, start: int, stop: int) -> ViewInputs:
    return jax.tree_util.tree_map(lambda a: a[start:stop], view)


def render_rows(count: int, chunk: int = RENDER_CHUNK) -> int:
    """The rows a view of ``count`` pixels is shaded in: the least of `RENDER_MIN_ROWS` · 2^k and
    1.5 · `RENDER_MIN_ROWS` · 2^k that holds them, up to ``chunk`` (a third of the rows padding at
    most), past it a multiple of ``chunk``. The demo's 8 views of 4,288 to 5,761 pixels: one
    compile of 6,144 rows instead of 8, 0.8 s each."""
    if count > chunk:
        return -(-count // chunk) * chunk
    size = RENDER_MIN_ROWS
    while size < count:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return min(size, chunk)


def _pad_rows(a, size: int, fill=None):
    """``a``'s rows followed by copies of its last row (or rows of ``fill``) up to ``size`` rows: on
    the host, as a pad run eagerly compiles once per shape; traced where ``a`` is (under a jit)."""
    traced = isinstance(a, jax.core.Tracer)
    xp, a = (jnp, a) if traced else (np, np.asarray(a))
    extra = size - a.shape[0]
    tail = xp.repeat(a[-1:], extra, 0) if fill is None else xp.full((extra,) + a.shape[1:], fill, a.dtype)
    out = xp.concatenate([a, tail])
    return out if traced else to_device(out)


def _pad(view: ViewInputs, ibl, size: int):
    """``view`` with its last row repeated up to ``size`` rows, and per-pixel integrals ``ibl``
    (`per_row`) with rows of 0 to match; other ``ibl`` as it is."""
    view = jax.tree_util.tree_map(lambda a: _pad_rows(a, size), view)
    if per_row(ibl):
        ibl = dataclasses.replace(ibl, table=_pad_rows(ibl.table, size, fill=0.0))
    return view, ibl


def radiance_view(
    view: ViewInputs,
    material: Material,
    model: Model = Model(),
    ibl=None,
    wrap: str = "repeat",
    normal_convention: str = "opengl",
    chunk: int = RENDER_CHUNK,
) -> Float[Array, "P 3"]:
    """Linear radiance of every shaded pixel of a view, in chunks of at most `chunk` pixels
    (per-pixel IBL integrals, ``model.ibl == "per_pixel"``, are the view's pixels' rows)."""
    count = view.num_pixels
    if count == 0:
        return jnp.zeros((0, 3), jnp.float32)
    per_pixel = per_row(ibl)
    # a view of one chunk is not sliced (a slice run eagerly compiles once per shape)
    whole = count <= chunk
    pieces = []
    for start in range(0, count, chunk):
        part = view if whole else _slice(view, start, min(start + chunk, count))
        rows = dataclasses.replace(ibl, table=ibl.table[start:start + chunk]) if per_pixel and not whole else ibl
        n = part.num_pixels
        size = render_rows(n, chunk) if whole else chunk  # padded: views of nearby sizes and chunks reuse a compilation
        if n < size:
            part, rows = _pad(part, rows, size)
        out = _radiance_chunk_jit(part, material, model, rows, wrap, normal_convention)
        pieces.append(out if n == size else out[:n])
    return pieces[0] if len(pieces) == 1 else jnp.concatenate(pieces, axis=0)


def render_view(
    view: ViewInputs,
    material: Material,
    model: Model = Model(),
    ibl=None,
    exposure: float = 0.0,
    tonemap: str = "none",
    color_space: str = "linear",
    wrap: str = "repeat",
    normal_convention: str = "opengl",
    background: Optional[Float[Array, "H W 3"]] = None,
) -> tuple[Float[Array, "H W 3"], Float[Array, "H W"]]:
    """Render a view to display values: (image (H, W, 3), alpha (H, W) = 1 where the mesh is hit).

    The image holds what a file of this capture holds: radiance × 2^exposure, tone mapped, and
    sRGB-encoded when `color_space` is "srgb". Pixels the mesh does not cover are 0 (or
    `background`, given as display values).

    The view's rows are padded to `render_rows` of them (repeats of its last hit, which write the
    same value again), so that its programs (the shading, the encoding, the scatter into the image)
    compile once per padded size, not once per view or `render --supersample` sample, whose hit
    counts all differ: a compile per sample took 84 s for `render --supersample 16` of a 96 x 96
    frame, against 10 s; `render --supersample 4` of the demo's capture 45 s against 11.5.
    """
    height, width = view.shape
    size = render_rows(view.num_pixels)
    if 0 < view.num_pixels < size:
        view, ibl = _pad(view, ibl, size)
    radiance = radiance_view(view, material, model, ibl, wrap, normal_convention)
    values = encode(radiance, exposure, tonemap, color_space)
    image = jnp.zeros((height * width, 3), jnp.float32) if background is None else jnp.asarray(
        background, jnp.float32
    ).reshape(height * width, 3)
    image = image.at[view.pixel].set(values.astype(jnp.float32))
    alpha = jnp.zeros((height * width,), jnp.float32).at[view.pixel].set(1.0)
    return image.reshape(height, width, 3), alpha.reshape(height, width)
