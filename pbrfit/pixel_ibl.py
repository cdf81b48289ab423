"""Per-pixel environment integrals: image-based lighting without the split sum, for fixed geometry.

The split sum (`pbrfit.ibl`) reads a map prefiltered as if n = v = R, which is off by tens of
percent under a sun (`experiments/ibl_accuracy.py`). A fit never moves the geometry: each pixel
keeps its n and v, only the material changes. For every BRDF of `pbrfit.model` the reflected
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
`pbrfit.brdf.energy_compensation`.) These are exactly `pbrfit.brdf.evaluate_cosines` regrouped;
`tests/test_pixel_ibl.py` checks them against `pbrfit.montecarlo.monte_carlo_radiance`.

Integration: per pixel and sample step, one direction from the environment's luminance
distribution, one cosine-weighted direction, and one GGX visible-normal direction per roughness
level; specular lobes combine (visible normals, environment) and diffuse lobes (cosine,
environment) by the balance heuristic (Veach 1997). The steps are the points of the R_7
quasi-random sequence (Roberts 2018), shifted per pixel by a hashed offset (Cranley-Patterson
rotation): unbiased, and at 256 samples 1.3% off a 4,096-sample reference where independent
uniforms were 4% off.
Every level reuses the same points, so the integrals are smooth in roughness, and Lambert's
lobes, which do not depend on it, are the same number at every level. Between levels I_k is interpolated by a
Catmull-Rom spline in r (C¹, so LM's roughness derivatives are continuous).

No occlusion: like the split sum, the environment reaches every point unblocked.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import os
from pathlib import Path
from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import brdf
from .environment import (Environment, direction_to_uv, dot3, from_environment_frame, sample_equirect,
                          to_environment_frame)
from .atomic import write_cache_file
from .model import Model
from .montecarlo import (_batch, _hash32, _uniforms, default_lut, environment_pdf, environment_sampler,
                         ggx_vndf_pdf, sample_cosine, sample_environment, sample_ggx_vndf, tangent_frame)

__all__ = ["PixelIBLSettings", "MIN_LEVELS", "MIN_SAMPLES", "MAX_LEVELS", "MAX_SAMPLES", "PixelIBL", "LOBES", "lobes_for", "pixel_ibl", "interpolate_lobes",
           "shade_pixel_ibl", "pixel_dfg"]

#: Every lobe a model can need (see the module docstring).
LOBES = ("dv", "dv_s", "dv_fd", "lambert", "lambert_s", "lambert_fd", "burley", "dfg_scale", "dfg_bias")
_SPECULAR = ("dv", "dv_s", "dv_fd")
_DIFFUSE = ("lambert", "lambert_s", "lambert_fd")
#: Pixels integrated per compiled call (the last chunk is padded), on the CPU and on an
#: accelerator: bounds memory; a GPU wants large calls (an H100 integrates 69,000 pixels in 0.34 s
#: in chunks of 16,384, 1.8 s in chunks of 2,048).
PIXEL_CHUNK = {"cpu": 2048, "accelerator": 16384}


#: The fewest roughness levels (a spline needs two nodes) and sample steps `PixelIBLSettings` takes.
MIN_LEVELS = 2
MIN_SAMPLES = 1
#: ... and the most: far beyond any use, and within the int32 counters of the jitted loops
#: (`pbrfit fit --ibl-levels`, `--ibl-samples`; `pbrfit synth --ibl-samples` for its Monte Carlo
#: renders).
MAX_LEVELS = 256
MAX_SAMPLES = 1 << 20


@dataclasses.dataclass(frozen=True)
class PixelIBLSettings:
    """Knobs of the per-pixel integrals; defaults chosen by `experiments/ibl_accuracy.py` (17
    levels: 9 are 2 to 3 times worse at n·v 0.1-0.3, 33 no better) and `experiments/env_fits.py`
    (512 samples: on sphere-env rendered by the Monte Carlo reference, 128 samples leave a
    well-observed roughness RMSE of 0.112 where 512 reach 0.069; `experiments/results/env_fits.json`).

    Attributes:
        levels: roughness grid r_j = j / (levels - 1), j = 0 .. levels - 1.
        samples: sample steps per pixel (each: one environment, one cosine and, per level, one
            visible-normal direction); the error of I_k falls roughly as 1/sqrt(samples).
        seed: seed of each pixel's random shift of its quasi-random sequence.
    """

    levels: int = 17
    samples: int = 512
    seed: int = 0

    def __post_init__(self):
        if not MIN_LEVELS <= int(self.levels) <= MAX_LEVELS:
            raise ValueError(f"PixelIBLSettings.levels must be from {MIN_LEVELS} to {MAX_LEVELS}, got {self.levels!r}")
        if not MIN_SAMPLES <= int(self.samples) <= MAX_SAMPLES:
            raise ValueError(f"PixelIBLSettings.samples must be from {MIN_SAMPLES} to {MAX_SAMPLES}, "
                             f"got {self.samples!r}")


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


# --- integration ---------------------------------------------------------------------------------

def _dv(model: Model, nv, nl, nh, rough):
    """D V (n·l) of the model's specular lobe (zero unless n·v > 0 and n·l > 0)."""
    nvc, nlc = jnp.clip(nv, 0.0, 1.0), jnp.clip(nl, 0.0, 1.0)
    return jnp.where((nv > 0) & (nl > 0), brdf.specular_dv(model, nvc, nlc, nh, rough) * nlc, 0.0)


@functools.partial(jax.jit, static_argnames=("model", "lobes", "levels", "samples", "batch"))
def _integrate(env, lut, n, v, first, seed, *, model, lobes, levels, samples, batch):
    radiance = env.radiance
    sampler = environment_sampler(radiance)
    dtype = n.dtype
    t, b = tangent_frame(n)
    nv = dot3(n, v)                                                   # (P,)
    v_loc = jnp.stack([dot3(v, t), dot3(v, b), nv], -1)
    rough = jnp.linspace(0.0, 1.0, levels, dtype=dtype)               # (R,)
    alpha = brdf.alpha_from_roughness(rough)
    to_world = lambda d: d[..., 0:1] * t + d[..., 1:2] * b + d[..., 2:3] * n  # noqa: E731
    spec = [k for k in lobes if k in _SPECULAR]
    diff = [k for k in lobes if k in _DIFFUSE]
    burley = "burley" in lobes

    def light(l):
        """Radiance arriving along world directions l and the environment technique's density there."""
        d = to_environment_frame(l, env.world_up, env.rotation_deg)
        return sample_equirect(radiance, direction_to_uv(d)), environment_pdf(sampler, d)

    def cosines(l):
        """(n·l, n·h, v·h) for directions l of shape (B, P, [R,] 3)."""
        extra = l.ndim - 2
        nv_ = nv.reshape(nv.shape + (1,) * (extra - 1))
        nl = dot3(n.reshape(n.shape[:1] + (1,) * (extra - 1) + (3,)), l)
        vl_sq = brdf.v_plus_l_sq(v.reshape(v.shape[:1] + (1,) * (extra - 1) + (3,)), l)
        nh, vh = brdf.half_vector_cosines(nv_, nl, None, vl_sq)
        return nl, nh, vh

    def spec_values(nl, nh, vh):
        """(B, P, R, Ks) specular lobe values at every level from the cosines of directions,
        (B, P, R) or (B, P, 1) (one direction for all levels)."""
        dv = _dv(model, nv[:, None], nl, nh, rough)
        s = brdf.f_schlick(vh, 0.0)
        out = {"dv": dv, "dv_s": dv * s}
        if "dv_fd" in spec:
            out["dv_fd"] = dv * brdf.f_dielectric(vh, model.ior)
        return jnp.stack([out[k] for k in spec], -1)

    def diff_values(l):
        """(B, P, Kd) r-independent diffuse lobe values and (B, P, R) Burley's, at directions l (B, P, 3)."""
        nl, _, vh = cosines(l)
        lit = (nv > 0) & (nl > 0)
        cos = jnp.where(lit, jnp.clip(nl, 0.0, 1.0), 0.0) / math.pi
        s = brdf.f_schlick(vh, 0.0)
        vals = {"lambert": cos, "lambert_s": cos * (1.0 - s)}
        if "lambert_fd" in diff:
            vals["lambert_fd"] = cos * (1.0 - brdf.f_dielectric(vh, model.ior))
        lam = jnp.stack([vals[k] for k in diff], -1) if diff else None
        bur = None
        if burley:
            fd = brdf.diffuse_burley(jnp.clip(nv, 0.0, 1.0)[:, None], jnp.clip(nl, 0.0, 1.0)[..., None],
                                     vh[..., None], rough)
            bur = fd * (math.pi * cos)[..., None]
        return lam, bur

    pixels = first + jnp.arange(n.shape[0], dtype=jnp.uint32)
    shift = _uniforms(_hash32(seed ^ _hash32(pixels)), jnp.zeros((1,), jnp.uint32), 7, jnp.float32)[0]  # (P, 7)
    safe = lambda x: jnp.where(x > 0, x, 1.0)  # noqa: E731
    zeros_r = jnp.zeros(n.shape[:1] + (levels, 3), dtype)

    def step(acc, k):
        spec_acc, diff_acc, bur_acc = acc
        u = _lattice(shift, k * batch + jnp.arange(batch, dtype=jnp.uint32), dtype)   # (B, P, 7)
        d_e, pe_e = sample_environment(sampler, u[..., 0:3])
        l_e = from_environment_frame(d_e, env.world_up, env.rotation_deg)                # (B, P, 3)
        L_e = sample_equirect(radiance, direction_to_uv(d_e))
        l_c = to_world(sample_cosine(u[..., 3:5]))
        L_c, pe_c = light(l_c)
        nl_e, nh_e, vh_e = cosines(l_e)
        nl_c, _, _ = cosines(l_c)
        pc = lambda nl: jnp.clip(nl, 0.0, 1.0) / math.pi  # noqa: E731
        if spec:
            v_lr = jnp.broadcast_to(v_loc[:, None, :], (n.shape[0], levels, 3))
            h = sample_ggx_vndf(v_lr, jnp.broadcast_to(alpha, v_lr.shape[:2]), u[..., None, 5:7])
            h = h[..., 0:1] * t[:, None] + h[..., 1:2] * b[:, None] + h[..., 2:3] * n[:, None]  # (B, P, R, 3)
            l_s = brdf.safe_normalize(2 * dot3(v[:, None, :], h)[..., None] * h - v[:, None, :])
            L_s, pe_s = light(l_s)
            nl_s, nh_s, vh_s = cosines(l_s)
            pv = lambda nl, nh: jnp.where(nl > 0, ggx_vndf_pdf(nv[:, None], nh, alpha), 0.0)  # noqa: E731
            w_s = L_s / safe(pv(nl_s, nh_s) + pe_s)[..., None]                              # (B, P, R, 3)
            e1 = (nl_e[..., None], nh_e[..., None], vh_e[..., None])                          # (B, P, 1)
            w_e = L_e[:, :, None, :] / safe(pv(*e1[:2]) + pe_e[..., None])[..., None]
            est = (spec_values(nl_s, nh_s, vh_s)[..., None] * w_s[..., None, :]
                   + spec_values(*e1)[..., None] * w_e[..., None, :])                          # (B, P, R, Ks, 3)
            spec_acc = spec_acc + jnp.sum(est, axis=0)
        if diff or burley:
            w_c = L_c / safe(pc(nl_c) + pe_c)[..., None]                                     # (B, P, 3)
            w_e2 = L_e / safe(pc(nl_e) + pe_e)[..., None]
            lam_c, bur_c = diff_values(l_c)
            lam_e, bur_e = diff_values(l_e)
            if diff:
                diff_acc = diff_acc + jnp.sum(lam_c[..., None] * w_c[..., None, :] + lam_e[..., None] * w_e2[..., None, :], 0)
            if burley:
                bur_acc = bur_acc + jnp.sum(bur_c[..., None] * w_c[:, :, None, :] + bur_e[..., None] * w_e2[:, :, None, :], 0)
        return (spec_acc, diff_acc, bur_acc), None

    acc0 = (jnp.zeros(n.shape[:1] + (levels, len(spec), 3), dtype), jnp.zeros(n.shape[:1] + (len(diff), 3), dtype),
            zeros_r)
    (spec_acc, diff_acc, bur_acc), _ = jax.lax.scan(step, acc0, jnp.arange(samples // batch, dtype=jnp.uint32))
    inv = 1.0 / (samples // batch * batch)
    parts = {}
    for i, name in enumerate(spec):
        parts[name] = spec_acc[:, :, i] * inv
    for i, name in enumerate(diff):
        parts[name] = jnp.broadcast_to(diff_acc[:, None, i] * inv, zeros_r.shape)
    if burley:
        parts["burley"] = bur_acc * inv
    if "dfg_scale" in lobes:
        from .brdf_lut import lookup_brdf_lut

        dfg = lookup_brdf_lut(lut, jnp.clip(nv, 0.0, 1.0)[:, None], jnp.broadcast_to(rough, nv.shape + (levels,)))
        parts["dfg_scale"] = jnp.broadcast_to(dfg[..., 0:1], zeros_r.shape)
        parts["dfg_bias"] = jnp.broadcast_to(dfg[..., 1:2], zeros_r.shape)
    return jnp.stack([parts[name] for name in lobes], axis=2)


def _golden(d: int) -> np.ndarray:
    """The additive recurrence α_i = φ_d^-(i+1), i < d, φ_d the root of x^(d+1) = x + 1 (Roberts 2018, "R_d")."""
    phi = 2.0
    for _ in range(64):
        phi = (1.0 + phi) ** (1.0 / (d + 1))
    return np.mod(phi ** -np.arange(1, d + 1, dtype=np.float64), 1.0)


_ALPHA7 = _golden(7)


def _lattice(shift, sample, dtype):
    """(len(sample), P, 7) quasi-random points: the R_7 sequence, shifted per pixel by ``shift``
    (P, 7), uniform random (Cranley-Patterson rotation), so each pixel's estimate is unbiased and
    its samples are spread evenly (error falling faster than 1/sqrt(samples) on smooth integrands)."""
    # k α mod 1 in exact integer arithmetic (24-bit fixed point), then shifted
    step = jnp.asarray(np.round(_ALPHA7 * (1 << 24)).astype(np.uint32))
    frac = ((sample[:, None] * step[None, :]) & jnp.uint32((1 << 24) - 1)).astype(jnp.float32) * (1.0 / (1 << 24))
    u = frac[:, None, :] + shift[None]
    return (u - jnp.floor(u)).astype(dtype)


#: Bump when the integrals change, so that cached tables of an older release are not read.
_CACHE_VERSION = "pixel-ibl-1"


def _cache_key(env: Environment, n: np.ndarray, v: np.ndarray, model: Model, settings: PixelIBLSettings) -> str:
    h = hashlib.sha256(_CACHE_VERSION.encode())
    h.update(repr((dataclasses.asdict(model.replace(ibl=None)), dataclasses.asdict(settings), env.world_up,
                   float(env.rotation_deg))).encode())
    for a in (np.asarray(env.radiance, np.float32), n, v):
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
              progress: Optional[Callable[[int, int], None]] = None) -> PixelIBL:
    """The lobe integrals of `lobes_for(model)` for points with unit normals n and view directions v.

    Pixels are integrated in chunks of ``chunk`` (default `PIXEL_CHUNK` for the default backend;
    one compilation, the last chunk padded), each pixel with its own quasi-random sequence, so
    the chunking changes only float rounding. With ``cache_dir`` the table is read from / written
    to ``cache_dir/pixel-ibl-<hash>.npy``, the hash covering the environment (radiance and
    orientation), n, v, the model's lobes and ``settings``. ``progress`` is called with (pixels
    done, pixels in all) after each chunk.
    """
    lobes = lobes_for(model)
    n = np.asarray(n, np.float32)
    v = np.asarray(v, np.float32)
    total = n.shape[0]
    levels, samples = int(settings.levels), int(settings.samples)
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"pixel-ibl-{_cache_key(env, n, v, model, settings)}.npy"
        cached = _load_cached(path, (total, levels, len(lobes), 3))
        if cached is not None:
            return PixelIBL(jnp.asarray(cached), lobes)
    if chunk is None:
        chunk = PIXEL_CHUNK["cpu" if jax.default_backend() == "cpu" else "accelerator"]
    size = max(1, min(int(chunk), total))
    batch = _batch(samples, size * levels)  # elements per sample step bounded as in the reference integrator
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
        part = _integrate(env, lut, jnp.asarray(nn), jnp.asarray(vv),
                          jnp.uint32(start), seed, model=model, lobes=lobes, levels=levels, samples=samples,
                          batch=batch)
        out.append(np.asarray(part)[: size - pad])
        if progress is not None:
            progress(start + size - pad, total)
    table = np.concatenate(out) if out else np.zeros((0, levels, len(lobes), 3), np.float32)
    if path is not None:
        _save_cached(path, table.astype(np.float32))
    return PixelIBL(jnp.asarray(table), lobes)


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
