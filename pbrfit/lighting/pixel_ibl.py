"""Per-pixel environment integrals: image-based lighting without the split sum, for fixed geometry.

The split sum (`pbrfit.lighting.ibl`) reads a map prefiltered as if n = v = R, which is off by tens of
percent under a sun (`experiments/ibl_accuracy.py`). A fit never moves the geometry: each pixel
keeps its n and v, only the material changes. For every BRDF of `pbrfit.physics.model` the reflected
environment radiance is a short sum of material coefficients times material-free integrals,

    L_o = ∫ f(l, v) L_env(l) (n·l) dω = Σ_k c_k(base_color, metallic) I_k(roughness),
    I_k(r) = ∫ g_k(l; n, v, r) L_env(l) (n·l) dω,

so the I_k can be integrated once per pixel on a grid of roughness values, and shading in the
fit becomes a lookup. What is left of the approximation is the Monte Carlo noise of the
precomputation and the interpolation over roughness, both set by `PixelIBLSettings` and measured
by `experiments/ibl_accuracy.py` and `experiments/env_fits.py`.

The lobes g_k (S = (1 - v·h)^5 is Schlick's weight, F_d the exact dielectric Fresnel at the
model's ior, DV the model's D × V, all masked to n·v > 0, n·l > 0):

    "dv"          DV                 "lambert"      1/π             (no specular lobe)
    "dv_s"        DV S               "lambert_s"    (1 - S)/π       (glTF: diffuse × (1 - F))
    "dv_fd"       DV F_d             "lambert_fd"   (1 - F_d)/π
    "burley"      Burley's f_d(r)    "dfg_scale", "dfg_bias"   the split-sum LUT's (scale, bias)
                                                               at (n·v, r) (multiscatter only)

and the coefficients (glTF 2.0 Appendix B: f0 = mix(0.04, c, m), c_diff = (1 - m) c, Schlick
F = f0 (1 - S) + S):

    fresnel "schlick":    spec = f0 (I_dv - I_dv_s) + I_dv_s,      diffuse = c_diff (1 - f0) I_lambert_s
    fresnel "dielectric": spec = (1 - m) I_dv_fd + m [c (I_dv - I_dv_s) + I_dv_s],
                          diffuse = c_diff [(1 - m) I_lambert_fd + m (1 - c) I_lambert_s]

(Burley's lobe and Lambert without a specular lobe carry no Fresnel weight: c_diff I; with
``multiscatter`` the specular part is multiplied by 1 + f0 (1 / (scale + bias) - 1), as
`pbrfit.physics.brdf.energy_compensation`.) These are exactly `pbrfit.physics.brdf.evaluate_cosines` regrouped;
`tests/test_pixel_ibl.py` checks them against `pbrfit.lighting.montecarlo.monte_carlo_radiance`.

Integration: `pbrfit.lighting.lobe_integrals` (quasi-Monte Carlo, multiple importance sampling, the same
points at every level, so the integrals are smooth in roughness). Between levels I_k is
interpolated by a Catmull-Rom spline in r (C¹, so LM's roughness derivatives are continuous).

Occlusion: given the pixels' `pbrfit.lighting.visibility.Visibility` (cast once by
`pbrfit.scene.occlusion`), every sample direction's radiance is multiplied by V(p, l), so the
integrals, and the shading, are those of the environment the mesh lets through; without it the
environment reaches every point unblocked. With a `pbrfit.lighting.visibility.Bounce` a blocked
direction brings the radiance the capture shows on the surface it hits instead of none: the
integrals stay linear in the light and free of the fitted material, so they are still computed
once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path
from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..physics import brdf
from .settings import MAX_LEVELS, MAX_SAMPLES, MIN_LEVELS, MIN_SAMPLES, PixelIBLSettings
from ..io.atomic import write_cache_file
from .environment import Environment
from .lobe_integrals import integrate_lobes
from ..physics.model import Model
from .montecarlo import default_lut, sample_batch
from .ibl import OccludedTables
from .visibility import Bounce, Visibility, visibility_rows

__all__ = ["per_row", "pixel_ibl_parts", "with_bounce", "PixelIBLSettings", "MIN_LEVELS", "MIN_SAMPLES", "MAX_LEVELS", "MAX_SAMPLES", "PixelIBL", "LOBES", "lobes_for", "pixel_ibl", "interpolate_lobes",
           "shade_pixel_ibl", "pixel_dfg"]

#: Every lobe a model can need (see the module docstring).
LOBES = ("dv", "dv_s", "dv_fd", "lambert", "lambert_s", "lambert_fd", "burley", "dfg_scale", "dfg_bias")
#: Pixels integrated per compiled call (the last chunk is padded), on the CPU and on an
#: accelerator: bounds memory; a GPU wants large calls (an H100 integrates 69,000 pixels in 0.34 s
#: in chunks of 16,384, 1.8 s in chunks of 2,048).
PIXEL_CHUNK = {"cpu": 2048, "accelerator": 16384}


class PixelIBL(eqx.Module):
    """Per-pixel lobe integrals I_k(r_j) (linear RGB) of one environment, and which lobes they are.

    Attributes:
        table: (P, R, K, 3) I_k at the R roughness levels, in the order of `lobes`.
        lobes: names of the K lobes (static), a subset of `LOBES` in that order.
    """

    table: Float[Array, "P R K 3"]
    lobes: tuple = eqx.field(static=True)

    @property
    def num_pixels(self) -> int:
        return int(self.table.shape[0])

    @property
    def levels(self) -> int:
        return int(self.table.shape[1])


def per_row(ibl) -> bool:
    """Whether ``ibl`` holds one row per point (a `PixelIBL`, or `pbrfit.lighting.ibl.OccludedTables`)
    in its ``table``, which goes with the points wherever they are sliced, padded or sharded."""
    return isinstance(ibl, (PixelIBL, OccludedTables))


def lobes_for(model: Model) -> tuple[str, ...]:
    """The lobes `model` reflects the environment through, in `LOBES` order."""
    need = set()
    schlick = model.fresnel == "schlick"
    if model.specular:
        if schlick or model.metallic:
            need |= {"dv", "dv_s"}
        if not schlick:
            need.add("dv_fd")
        if model.multiscatter:
            need |= {"dfg_scale", "dfg_bias"}
    if model.diffuse == "lambert":
        if not model.specular:
            need.add("lambert")
        else:
            if schlick or model.metallic:
                need.add("lambert_s")
            if not schlick:
                need.add("lambert_fd")
    elif model.diffuse == "burley":
        need.add("burley")
    return tuple(name for name in LOBES if name in need)


#: Bump when the integrals change, so that cached tables of an older release are not read.
_CACHE_VERSION = "pixel-ibl-2"


def _cache_key(env: Environment, n: np.ndarray, v: np.ndarray, model: Model, settings: PixelIBLSettings,
               visibility: Optional[Visibility], bounce: Optional[Bounce]) -> str:
    h = hashlib.sha256(_CACHE_VERSION.encode())
    h.update(repr((dataclasses.asdict(model.replace(ibl=None)), dataclasses.asdict(settings), env.world_up,
                   float(env.rotation_deg))).encode())
    seen = () if visibility is None else tuple(np.asarray(a) for a in (visibility.labels, visibility.bits,
                                                                      visibility.normal))
    h.update(b"occluded" if seen else b"open")
    if bounce is not None:
        seen = seen + (np.asarray(bounce.radiance, np.float32), np.asarray(bounce.offsets, np.int64))
        h.update(b"bounce")
    for a in (np.asarray(env.radiance, np.float32), n, v) + seen:
        h.update(repr(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:32]


def _load_cached(path: Path, shape: tuple) -> Optional[np.ndarray]:
    try:
        table = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):  # missing or damaged: recompute
        return None
    return table if table.shape == shape and table.dtype == np.float32 else None


def _save_cached(path: Path, table: np.ndarray) -> None:
    write_cache_file(path, lambda f: np.save(f, table))


def pixel_ibl(env: Environment, n: Float[Array, "P 3"], v: Float[Array, "P 3"], model: Model = Model(),
              settings: PixelIBLSettings = PixelIBLSettings(), chunk: Optional[int] = None,
              cache_dir: Optional[os.PathLike] = None,
              progress: Optional[Callable[[int, int], None]] = None,
              visibility: Optional[Visibility] = None, bounce: Optional[Bounce] = None) -> PixelIBL:
    """The lobe integrals of `lobes_for(model)` for points with unit normals n and view directions v,
    occluded by ``visibility`` (one row per point; None: unoccluded), its blocked directions lit
    by ``bounce`` (`pbrfit.lighting.visibility.Bounce`; None: dark): `pixel_ibl_parts` added up."""
    direct, bounced = pixel_ibl_parts(env, n, v, model, settings, chunk, cache_dir, progress, visibility, bounce)
    return direct if bounced is None else with_bounce(direct, bounced)


def with_bounce(direct: PixelIBL, bounced: PixelIBL) -> PixelIBL:
    """The integrals of the light of both parts of `pixel_ibl_parts` (the dfg lobes, which hold no
    light, once)."""
    light = jnp.asarray([name not in ("dfg_scale", "dfg_bias") for name in direct.lobes], direct.table.dtype)
    return PixelIBL(direct.table + bounced.table * light[:, None], direct.lobes)


def pixel_ibl_parts(env: Environment, n: Float[Array, "P 3"], v: Float[Array, "P 3"], model: Model = Model(),
                    settings: PixelIBLSettings = PixelIBLSettings(), chunk: Optional[int] = None,
                    cache_dir: Optional[os.PathLike] = None,
                    progress: Optional[Callable[[int, int], None]] = None,
                    visibility: Optional[Visibility] = None,
                    bounce: Optional[Bounce] = None) -> tuple[PixelIBL, Optional[PixelIBL]]:
    """The lobe integrals of `lobes_for(model)` for points with unit normals n and view directions v,
    of the environment's light that arrives past ``visibility`` (one row per point; None:
    unoccluded), and of the light ``bounce`` brings along the blocked directions (None where no
    bounce is given), from the same samples: (direct, bounced).

    Pixels are integrated in chunks of ``chunk`` (default `PIXEL_CHUNK` for the default backend;
    one compilation, the last chunk padded), each pixel with its own quasi-random sequence, so
    the chunking changes only float rounding. With ``cache_dir`` the table is read from / written
    to ``cache_dir/pixel-ibl-<hash>.npy``, the hash covering the environment (radiance and
    orientation), n, v, the model's lobes, ``settings``, ``visibility`` and ``bounce``. ``progress`` is called
    with (pixels done, pixels in all) after each chunk.
    """
    lobes = lobes_for(model)
    n = np.asarray(n, np.float32)
    v = np.asarray(v, np.float32)
    total = n.shape[0]
    if bounce is not None and (visibility is None or len(bounce.offsets) != total + 1):
        raise ValueError("bounce: needs the visibility it was cast with, one row per point")
    if visibility is not None and (visibility.num_points != total
                                   or tuple(visibility.labels.shape) != tuple(env.radiance.shape[:2])):
        raise ValueError(f"visibility: {visibility.num_points} rows on {tuple(visibility.labels.shape)} cells' texels, "
                         f"for {total} points under a {tuple(env.radiance.shape[:2])} environment")
    levels, samples = int(settings.levels), int(settings.samples)
    channels = 3 if bounce is None else 6
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"pixel-ibl-{_cache_key(env, n, v, model, settings, visibility, bounce)}.npy"
        cached = _load_cached(path, (total, levels, len(lobes), channels))
        if cached is not None:
            return _parts(cached, lobes)
    if chunk is None:
        chunk = PIXEL_CHUNK["cpu" if jax.default_backend() == "cpu" else "accelerator"]
    size = max(1, min(int(chunk), total))
    batch = sample_batch(samples, size * levels)  # elements per sample step bounded as in the reference integrator
    lut = jnp.asarray(default_lut(model), jnp.float32) if "dfg_scale" in lobes else jnp.zeros((1, 1, 2), jnp.float32)
    env = dataclasses.replace(env, radiance=jnp.asarray(env.radiance, jnp.float32))
    seed = jnp.uint32(int(settings.seed) & 0xFFFFFFFF)
    out = []
    for start in range(0, total, size):
        nn, vv = n[start:start + size], v[start:start + size]
        pad = size - nn.shape[0]
        if pad:
            nn = np.concatenate([nn, np.tile(np.float32([0, 0, 1]), (pad, 1))])
            vv = np.concatenate([vv, np.tile(np.float32([0, 0, 1]), (pad, 1))])
        vis = None if visibility is None else visibility_rows(visibility, start, start + size - pad, pad, bounce)
        part = integrate_lobes(env, lut, jnp.asarray(nn), jnp.asarray(vv),
                               jnp.uint32(start), seed, vis, model=model, lobes=lobes, levels=levels,
                               samples=samples, batch=batch)
        out.append(np.asarray(part)[: size - pad])
        if progress is not None:
            progress(start + size - pad, total)
    table = np.concatenate(out) if out else np.zeros((0, levels, len(lobes), channels), np.float32)
    if path is not None:
        _save_cached(path, table.astype(np.float32))
    return _parts(table, lobes)


def _parts(table: np.ndarray, lobes: tuple) -> tuple[PixelIBL, Optional[PixelIBL]]:
    """(direct, bounced) `PixelIBL` of a table of 3 or 6 channels (`pixel_ibl_parts`)."""
    direct = PixelIBL(jnp.asarray(table[..., :3]), lobes)
    return direct, (PixelIBL(jnp.asarray(table[..., 3:]), lobes) if table.shape[-1] == 6 else None)


# --- shading -------------------------------------------------------------------------------------

def interpolate_lobes(table: Float[Array, "P R K 3"], roughness: Float[Array, " P"]) -> Float[Array, "P K 3"]:
    """I_k at each pixel's roughness: Catmull-Rom in r over the uniform grid (C¹, error O(h³),
    exact for quadratics). The end intervals take their outer point from the parabola through
    the three nearest levels, so they keep that order."""
    levels = table.shape[1]
    # (clamped with where, not clip: at r = 0 or 1 exactly the derivative is the spline's, not half of it)
    x = jnp.where(roughness < 0.0, 0.0, jnp.where(roughness > 1.0, 1.0, roughness)) * (levels - 1)
    i = jnp.clip(jnp.floor(x), 0, levels - 2).astype(jnp.int32)
    s = (x - i)[:, None, None]
    take = lambda j: jnp.take_along_axis(table, jnp.clip(j, 0, levels - 1)[:, None, None, None], axis=1)[:, 0]  # noqa: E731
    p1, p2 = take(i), take(i + 1)
    before, after = take(i - 1), take(i + 2)
    if levels >= 3:  # outer points of the end intervals: the parabola through the three nearest levels
        p0 = jnp.where((i > 0)[:, None, None], before, 3 * (p1 - p2) + after)
        p3 = jnp.where((i < levels - 2)[:, None, None], after, 3 * (p2 - p1) + before)
    else:
        p0, p3 = 2 * p1 - p2, 2 * p2 - p1
    return 0.5 * (2 * p1 + (p2 - p0) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s * s
                  + (3 * (p1 - p2) + p3 - p0) * s * s * s)


def pixel_dfg(ibl: PixelIBL, lobes_at: Float[Array, "P K 3"]) -> Float[Array, "P 2"]:
    """The split-sum (scale, bias) at each pixel's n·v and roughness, from interpolated lobes."""
    k = ibl.lobes.index("dfg_scale")
    return jnp.stack([lobes_at[:, k, 0], lobes_at[:, k + 1, 0]], -1)


def shade_pixel_ibl(ibl: PixelIBL, base_color: Float[Array, "P 3"], metallic: Float[Array, "P 1"],
                    roughness: Float[Array, "P 1"], model: Model = Model()) -> Float[Array, "P 3"]:
    """Environment light reflected by each pixel's material: Σ_k c_k I_k(r) (module docstring).

    ``ibl`` must have been integrated for ``model`` (`lobes_for`); metallic and roughness may be
    (P, 1) or (P,). Differentiable in the material; exact up to the table's noise and the
    interpolation in roughness.
    """
    if ibl.lobes != lobes_for(model):
        raise ValueError(f"per-pixel IBL integrated for lobes {ibl.lobes}, but the model needs {lobes_for(model)}")
    col = lambda x: x[..., None] if jnp.ndim(x) == jnp.ndim(base_color) - 1 else x  # noqa: E731
    metallic, roughness = col(jnp.asarray(metallic)), col(jnp.asarray(roughness))
    at = interpolate_lobes(ibl.table, roughness[..., 0])
    lobe = {name: at[:, i] for i, name in enumerate(ibl.lobes)}
    f0 = brdf.specular_f0(base_color, metallic, model)
    c_diff = brdf.diffuse_color(base_color, metallic, model)
    out = jnp.zeros(jnp.broadcast_shapes(jnp.shape(f0), at.shape[:1] + (3,)), f0.dtype)
    schlick = model.fresnel == "schlick"
    if model.specular:
        if schlick:
            spec = f0 * (lobe["dv"] - lobe["dv_s"]) + lobe["dv_s"]
        else:
            spec = lobe["dv_fd"]
            if model.metallic:
                metal = base_color * (lobe["dv"] - lobe["dv_s"]) + lobe["dv_s"]
                spec = (1.0 - metallic) * spec + metallic * metal
        if model.multiscatter:
            spec = spec * brdf.energy_compensation(f0, pixel_dfg(ibl, at))
        out = out + spec
    if model.diffuse == "lambert":
        if not model.specular:
            out = out + c_diff * lobe["lambert"]
        elif schlick:
            out = out + c_diff * (1.0 - f0) * lobe["lambert_s"]
        else:
            w = lobe["lambert_fd"]
            if model.metallic:
                w = (1.0 - metallic) * w + metallic * (1.0 - base_color) * lobe["lambert_s"]
            out = out + c_diff * w
    elif model.diffuse == "burley":
        out = out + c_diff * lobe["burley"]
    return out
