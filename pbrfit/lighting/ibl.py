"""Split-sum image-based lighting (Karis 2013): irradiance, prefiltered specular, BRDF LUT, shading.

The environment's reflected radiance ∫ f L_env (n·l) dω is split into products of
environment-only and BRDF-only integrals, each tabulated once per environment (or once ever):

    diffuse   ≈ c_diff · E(n)/π · A_d(n·v, r)             E/π: SH9 or a cosine-convolved map
    specular  ≈ L_pre(R, r) · (F0 · scale(n·v, r) + F90 · bias(n·v, r))

with R = reflect(-v, n) (the default ``specular_direction="dominant"`` reads it along a direction
bent from R towards n with roughness; `IBLSettings`). ``L_pre`` is the environment prefiltered with the GGX lobe under the
N = V = R assumption; (scale, bias) is the BRDF LUT. The diffuse factor A_d is the directional
albedo of the glTF diffuse lobe itself, ∫ (1 - F(v·h)) f_d (n·l) dω for the model's f_d and
Fresnel (for Lambert and Schlick: (1 - F0) ∫ (1 - (1 - v·h)^5) (n·l)/π dω), tabulated like the
LUT. With that choice the split sum is exact under a constant environment, where the ground truth
`monte_carlo_radiance` and it must agree. (Filament weights by 1 - (F0 scale + bias) instead, and
glTF-Sample-Viewer by Fdez-Agüera's single/multi-scatter split; both differ from the glTF BRDF by a
few percent at grazing angles.)

The BRDF tables (scale, bias and A_d) live in `pbrfit.lighting.brdf_lut`; this module re-exports them.

Occlusion: the tables assume every direction of the environment reaches every point. For fixed
geometry that blocks some, `OccludedTables` carries per-point factors
(`pbrfit.lighting.visibility.split_sum_factors`): the irradiance term is multiplied by the share
of the irradiance that arrives, the prefiltered term by the share of the specular lobe's light
that arrives at the point's roughness; `experiments/occlusion.py` measures how close that comes
to the occluded per-pixel integrals.

Sources: B. Karis, "Real Shading in Unreal Engine 4", SIGGRAPH 2013; R. Ramamoorthi &
P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps", SIGGRAPH 2001;
J. Křivánek & M. Colbert, "Real-time Shading with Filtered Importance Sampling", EGSR 2008;
Filament, "Physically Based Rendering in Filament", sections 5.3 and 4.7.2 (multi-scattering).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..physics import brdf
from .environment import (Environment, direction_to_uv, dot3, environment_lookup, load_environment,
                          mip_pyramid, resample_equirect, sample_equirect, sample_stack, stack_levels,
                          texel_directions, texel_solid_angles, to_environment_frame)
from .brdf_lut import _specular_tables, brdf_lut, diffuse_lut, lookup_brdf_lut, lookup_table, specular_albedo
from ..physics.model import Model
from .montecarlo import monte_carlo_radiance
from .sampling import hammersley, tangent_frame
from .visibility import factors_at

__all__ = [
    "Environment",
    "load_environment",
    "environment_lookup",
    "IBLSettings",
    "IBLTables",
    "OccludedTables",
    "build_ibl",
    "brdf_tables",
    "brdf_lut",
    "specular_albedo",
    "diffuse_lut",
    "lookup_brdf_lut",
    "lookup_table",
    "sh9_coefficients",
    "sh9_irradiance",
    "irradiance_map",
    "prefilter_level",
    "prefiltered_lookup",
    "irradiance_lookup",
    "shade_ibl",
    "monte_carlo_radiance",
]

#: Coarsest prefiltered level height: an 8 x 16 map still resolves a GGX lobe at roughness 1.
PREFILTER_MIN_HEIGHT = 8
#: Prefiltered resolution halves per this much perceptual roughness. The lobe widens roughly as
#: alpha = r^2, so resolution can fall as roughness grows; 0.2 keeps two or more texels across the
#: lobe from roughness 0.2 up with the default 128-row level 0.
PREFILTER_ROUGHNESS_PER_OCTAVE = 0.2
#: Source height for the cosine-convolved irradiance map: twice the map's, at least this. The
#: clamped-cosine kernel is smooth, but a sun box-filtered into a 32-row source put the map's
#: texels 1.3% off under a 60° sun; from 64 rows they are within 1e-4.
IRRADIANCE_SOURCE_MIN_HEIGHT = 64


@dataclasses.dataclass(frozen=True)
class IBLSettings:
    """Knobs of the split sum. Defaults chosen by `experiments/ibl_accuracy.py` (see docs/ibl.md).

    Attributes:
        lut_size: BRDF LUT entries per axis (n·v and perceptual roughness).
        lut_samples: Hammersley samples per LUT entry (GGX visible-normal sampling).
        prefilter_levels: prefiltered levels, level i at roughness i / (levels - 1).
        prefilter_resolution: height of level 0 (width is twice); rougher levels are coarser,
            halving per `PREFILTER_ROUGHNESS_PER_OCTAVE`, down to `PREFILTER_MIN_HEIGHT`.
        prefilter_samples: GGX samples per prefiltered texel (filtered importance sampling).
        prefilter_lod_bias: Křivánek & Colbert's mip bias (1 in the paper; larger blurs more).
        irradiance: ``"map"`` (a cosine-convolved map; default: no ringing around a sun) or
            ``"sh9"`` (9 spherical-harmonic coefficients; as accurate under smooth light).
        irradiance_resolution: height of the irradiance map (``"map"`` only; width is twice).
        env_resolution: the environment is box-filtered down to at most this height before
            anything is built (the Monte Carlo reference always reads the full map).
        specular_direction: ``"dominant"`` (default) reads the prefiltered map along
            normalize(mix(R, n, alpha)) with alpha = roughness², an approximation of the lobe's
            dominant direction for rough surfaces in the family of Lagarde & de Rousiers 2014
            (section 4.9.3) and Filament's getSpecularDominantDirection, whose weights differ
            (Filament's is alpha², Lagarde's a fit in alpha; these were not compared here);
            ``"reflect"`` along R = reflect(-v, n) (Karis 2013). `experiments/ibl_accuracy.py`
            measures this direction against ``"reflect"``. The dominant direction cuts the error by a third
            under smooth light and most at grazing angles.
    """

    lut_size: int = 32
    lut_samples: int = 512
    prefilter_levels: int = 6
    prefilter_resolution: int = 128
    prefilter_samples: int = 64
    prefilter_lod_bias: float = 1.0
    irradiance: str = "map"
    irradiance_resolution: int = 32
    env_resolution: int = 256
    specular_direction: str = "dominant"

    def __post_init__(self):
        if self.irradiance not in ("sh9", "map"):
            raise ValueError(f"IBLSettings.irradiance must be 'sh9' or 'map', got {self.irradiance!r}")
        for name in ("lut_size", "lut_samples", "prefilter_resolution", "prefilter_samples",
                     "irradiance_resolution", "env_resolution"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"IBLSettings.{name} must be >= 1, got {getattr(self, name)!r}")
        if self.specular_direction not in ("reflect", "dominant"):
            raise ValueError(f"IBLSettings.specular_direction must be 'reflect' or 'dominant', got {self.specular_direction!r}")
        if self.prefilter_levels < 2:
            raise ValueError(f"IBLSettings.prefilter_levels must be >= 2, got {self.prefilter_levels!r}")


class IBLTables(eqx.Module):
    """Everything the split sum reads, built once per environment by `build_ibl`.

    Attributes:
        irradiance: (9, 3) SH9 coefficients of the radiance, or an (h, 2h, 3) map of E/π.
        prefiltered: (levels, H, W, 3) padded stack; level k is ``level_shapes[k]`` in its corner.
        lut: (size, size, 2) BRDF LUT, see `brdf_lut`.
        diffuse: (size, size, 3) diffuse directional albedo tables, see `diffuse_lut`.
        dielectric: (size, size, 1) specular directional albedo with the exact dielectric Fresnel
            at the model's ior (used when ``model.fresnel == "dielectric"``), laid out like `lut`.
    """

    irradiance: Float[Array, "..."]
    prefiltered: Float[Array, "L H W 3"]
    lut: Float[Array, "S S 2"]
    diffuse: Float[Array, "S S 3"]
    dielectric: Float[Array, "S S 1"]
    irradiance_kind: str = eqx.field(static=True, default="sh9")
    level_shapes: tuple = eqx.field(static=True, default=())
    world_up: str = eqx.field(static=True, default="+y")
    rotation_deg: float = eqx.field(static=True, default=0.0)
    specular_direction: str = eqx.field(static=True, default="reflect")


class OccludedTables(eqx.Module):
    """Split-sum tables with per-point occlusion factors.

    Attributes:
        tables: the environment's `IBLTables`.
        table: (P, S) each point's `pbrfit.lighting.visibility.split_sum_factors` (k_d, then
            k_s on its roughness levels); one row per point, as `pbrfit.lighting.pixel_ibl.PixelIBL`'s.
    """

    tables: IBLTables
    table: Float[Array, "P S"]

    @property
    def num_pixels(self) -> int:
        return int(self.table.shape[0])


# --- irradiance ----------------------------------------------------------------------------------

# Ramamoorthi & Hanrahan 2001, eq. 12-13: real SH basis constants and the cosine-lobe constants.
_SH_Y = (0.282095, 0.488603, 1.092548, 0.315392, 0.546274)
_SH_C = (0.429043, 0.511664, 0.743125, 0.886227, 0.247708)


def _sh9_basis(d):
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    y0, y1, y2, y3, y4 = _SH_Y
    return jnp.stack([y0 + 0 * x, y1 * y, y1 * z, y1 * x, y2 * x * y, y2 * y * z, y3 * (3 * z * z - 1),
                      y2 * x * z, y4 * (x * x - y * y)], -1)   # L00, L1-1, L10, L11, L2-2, L2-1, L20, L21, L22


@jax.jit
def sh9_coefficients(radiance: Float[Array, "H W 3"]) -> Float[Array, "9 3"]:
    """Project an environment-frame equirect onto 9 real SH: L_lm = Σ L(ω) Y_lm(ω) Ω (exact texel Ω)."""
    h, w, _ = radiance.shape
    basis = _sh9_basis(jnp.asarray(texel_directions(h, w), radiance.dtype))
    omega = jnp.asarray(texel_solid_angles(h, w), radiance.dtype)[..., None]
    return jnp.einsum("hwk,hwc->kc", basis * omega, radiance, precision=jax.lax.Precision.HIGHEST)


@jax.jit
def sh9_irradiance(coeffs: Float[Array, "9 3"], n: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """E(n)/π from SH9 coefficients, environment-frame unit normals (R&H 2001, eq. 13):

    E = c1 L22 (x²-y²) + c3 L20 z² + c4 L00 - c5 L20 + 2 c1 (L2-2 xy + L21 xz + L2-1 yz)
        + 2 c2 (L11 x + L1-1 y + L10 z).
    """
    c1, c2, c3, c4, c5 = _SH_C
    x, y, z = (n[..., k:k + 1] for k in range(3))
    L = coeffs
    e = (c1 * L[8] * (x * x - y * y) + c3 * L[6] * z * z + c4 * L[0] - c5 * L[6]
         + 2 * c1 * (L[4] * x * y + L[7] * x * z + L[5] * y * z)
         + 2 * c2 * (L[3] * x + L[1] * y + L[2] * z))
    return e / math.pi


def irradiance_map(radiance: Float[Array, "H W 3"], height: int) -> Float[Array, "h 2h 3"]:
    """E/π on an (height, 2 height) equirect by brute-force cosine convolution of a box-filtered source.

    E(n)/π = (1/π) Σ_k L_k max(0, n·ω_k) Ω_k over the source texels k (exact solid angles Ω_k),
    with the weights normalised to sum to 1 (their exact integral), so a constant stays exact.
    The weights depend on the shapes alone: they are formed once per shape pair, outside the
    compiled program, and passed to it (as a constant they would be lowered into its text).
    """
    return _convolve_irradiance(radiance, _irradiance_kernel(radiance.shape[0], height, radiance.dtype))


def _irradiance_kernel(source_height: int, height: int, dtype) -> Float[Array, "n m"]:
    hs = min(source_height, max(2 * height, IRRADIANCE_SOURCE_MIN_HEIGHT))
    return jnp.asarray(_cosine_weights(hs, height), dtype)


@functools.lru_cache(maxsize=8)
def _cosine_weights(source_height: int, height: int) -> np.ndarray:
    ds = texel_directions(source_height, 2 * source_height).reshape(-1, 3)
    om = np.broadcast_to(texel_solid_angles(source_height, 2 * source_height),
                         (source_height, 2 * source_height)).reshape(-1)
    dn = texel_directions(height, 2 * height).reshape(-1, 3)
    kernel = dn @ ds.T                          # in place from here: one (n, m) array, not three
    np.maximum(kernel, 0.0, out=kernel)
    kernel *= om[None, :]
    kernel /= kernel.sum(1, keepdims=True)      # = (1/π) Σ max(0, n·ω) Ω, exactly 1 once discretised
    kernel.flags.writeable = False
    return kernel


@jax.jit
def _convolve_irradiance(radiance, kernel):
    """`irradiance_map` given its weights (height·2height, source texels)."""
    height = math.isqrt(kernel.shape[0] // 2)
    hs = math.isqrt(kernel.shape[1] // 2)
    src = resample_equirect(radiance, hs, 2 * hs)
    out = jnp.matmul(kernel, src.reshape(-1, 3), precision=jax.lax.Precision.HIGHEST)
    return out.reshape(height, 2 * height, 3)


@jax.jit
def irradiance_lookup(tables: IBLTables, n_env: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """E/π at environment-frame normals, from whichever representation the tables hold."""
    if tables.irradiance_kind == "sh9":
        return jnp.maximum(sh9_irradiance(tables.irradiance, n_env), 0.0)
    return sample_equirect(tables.irradiance, direction_to_uv(n_env))


# --- prefiltered specular ------------------------------------------------------------------------

def _level_height(settings: IBLSettings, roughness: float) -> int:
    h = settings.prefilter_resolution * 2.0 ** (-roughness / PREFILTER_ROUGHNESS_PER_OCTAVE)
    return int(max(PREFILTER_MIN_HEIGHT, min(settings.prefilter_resolution, round(h))))


def _prefilter_samples(roughness: float, samples: int, source_height: int, lod_bias: float):
    """Static (numpy) sample set for one level: local l, weight n·l, and source mip per sample.

    With N = V the density of l is D(h)(n·h)/(4 v·h) = D(h)/4; a sample stands for the solid
    angle Ω_s = 1/(samples · pdf), a level-0 texel at the equator for Ω_p = (π/H)², so the mip is
    max(0, ½ log2(Ω_s/Ω_p) + bias) (Křivánek & Colbert 2008, eq. 13).
    """
    alpha = max(roughness, brdf.MIN_ROUGHNESS) ** 2
    u = hammersley(samples)
    a2 = alpha * alpha
    c2 = (1.0 - u[:, 0]) / (1.0 + (a2 - 1.0) * u[:, 0])
    c, s = np.sqrt(c2), np.sqrt(np.clip(1 - c2, 0, 1))
    phi = 2 * np.pi * u[:, 1]
    h = np.stack([s * np.cos(phi), s * np.sin(phi), c], -1)
    l = 2 * c[:, None] * h - np.array([0.0, 0.0, 1.0])
    d = a2 / (np.pi * ((1 - c) * (1 + c) + c2 * a2) ** 2)
    omega_s = 1.0 / (samples * d / 4.0)
    omega_p = (np.pi / source_height) ** 2
    lod = np.maximum(0.0, 0.5 * np.log2(omega_s / omega_p) + lod_bias)
    keep = l[:, 2] > 0
    return l[keep], l[keep, 2], lod[keep]


def prefilter_level(stack, shapes, roughness: float, height: int, samples: int, lod_bias: float = 1.0):
    """One prefiltered level (height, 2 height, 3) at perceptual ``roughness`` from a source mip stack.

    L_pre(N) = Σ_k L(l_k) (n·l_k) / Σ_k (n·l_k), l_k from GGX samples around N = V = R (Karis 2013),
    each read at its filtered-importance-sampling mip (see `_prefilter_samples`).
    """

    l, w, lod = _prefilter_samples(roughness, samples, shapes[0][0], lod_bias)
    n = jnp.asarray(texel_directions(height, 2 * height).reshape(-1, 3), stack.dtype)
    t, b = tangent_frame(n)

    def step(acc, x):
        lk, wk, lodk = x
        d = lk[0] * t + lk[1] * b + lk[2] * n
        return acc + wk * sample_stack(stack, shapes, direction_to_uv(d), jnp.broadcast_to(lodk, d.shape[:-1])), None

    xs = (jnp.asarray(l, stack.dtype), jnp.asarray(w, stack.dtype), jnp.asarray(lod, stack.dtype))
    acc, _ = jax.lax.scan(step, jnp.zeros_like(n), xs)
    return (acc / float(w.sum())).reshape(height, 2 * height, 3)


@jax.jit
def prefiltered_lookup(tables: IBLTables, r_env: Float[Array, "*b 3"], roughness) -> Float[Array, "*b 3"]:
    """Prefiltered radiance along environment-frame directions at continuous perceptual roughness."""
    k = tables.prefiltered.shape[0]
    level = brdf.clamp_inward(roughness, 0.0, 1.0) * (k - 1)
    return sample_stack(tables.prefiltered, tables.level_shapes, direction_to_uv(r_env), level)


# --- building and shading ------------------------------------------------------------------------

@functools.partial(jax.jit, static_argnames=("settings",))
def _build(radiance, irradiance_kernel, settings: IBLSettings):
    h, w, _ = radiance.shape
    if h > settings.env_resolution:
        hs = settings.env_resolution
        radiance = resample_equirect(radiance, hs, max(1, round(w * hs / h)))
    stack, shapes = stack_levels(mip_pyramid(radiance))
    if settings.irradiance == "sh9":
        irr = sh9_coefficients(radiance)
    else:
        irr = _convolve_irradiance(radiance, irradiance_kernel)
    levels = []
    for i in range(settings.prefilter_levels):
        r = i / (settings.prefilter_levels - 1)
        levels.append(prefilter_level(stack, shapes, r, _level_height(settings, r), settings.prefilter_samples,
                                      settings.prefilter_lod_bias))
    pre, _ = stack_levels(levels)
    return irr, pre


def _prefiltered_shapes(settings: IBLSettings) -> tuple:
    hs = [_level_height(settings, i / (settings.prefilter_levels - 1)) for i in range(settings.prefilter_levels)]
    return tuple((h, 2 * h) for h in hs)


def build_ibl(env: Environment, settings: IBLSettings = IBLSettings(), model: Optional[Model] = None) -> IBLTables:
    """Split-sum tables for ``env``: irradiance, prefiltered stack, BRDF LUT and diffuse tables.

    Jittable and differentiable w.r.t. ``env.radiance``. ``model`` picks the LUT's specular lobe
    and the diffuse lobe tabulated (default `Model()`, the glTF BRDF).
    """
    model = model or Model()
    kernel = None
    if settings.irradiance != "sh9":
        kernel = _irradiance_kernel(min(env.radiance.shape[0], settings.env_resolution),
                                    settings.irradiance_resolution, env.radiance.dtype)
    irr, pre = _build(env.radiance, kernel, settings)
    shapes = _prefiltered_shapes(settings)
    spec = _specular_tables(settings.lut_size, settings.lut_samples, model).astype(pre.dtype)
    dif = diffuse_lut(settings.lut_size, settings.lut_samples, model).astype(pre.dtype)
    return IBLTables(irr, pre, spec[..., :2], dif, spec[..., 2:], settings.irradiance, shapes,
                     env.world_up, env.rotation_deg, settings.specular_direction)


def brdf_tables(settings: IBLSettings = IBLSettings(), model: Optional[Model] = None,
                dtype=jnp.float32) -> IBLTables:
    """The split sum's BRDF tables alone (LUT, diffuse and dielectric albedo), with an empty
    environment (black irradiance, one black prefiltered texel): what ``Model(multiscatter=True)``
    reads for its energy compensation (`brdf.energy_compensation`, the DFG LUT) under punctual
    lights alone, where there is no environment to build `build_ibl` from. In ``dtype`` (as
    `build_ibl`'s are in the environment's), so that shading float32 inputs stays float32 with
    x64 enabled."""
    model = model or Model()
    spec = _specular_tables(settings.lut_size, settings.lut_samples, model).astype(dtype)
    dif = diffuse_lut(settings.lut_size, settings.lut_samples, model).astype(dtype)
    return IBLTables(jnp.zeros((9, 3), spec.dtype), jnp.zeros((1, 1, 1, 3), spec.dtype), spec[..., :2], dif,
                     spec[..., 2:], "sh9", ((1, 1),))


def _diffuse_albedo(tables, n_dot_v, roughness, base_color, metallic, f0, model):
    """∫ (diffuse weight) f_d (n·l) dω for a white diffuse color, as `brdf.evaluate_cosines` weights it."""
    t = lookup_table(tables.diffuse, n_dot_v, roughness)
    if not (model.diffuse == "lambert" and model.specular):
        return t[..., 1:2]                          # no Fresnel weight on the diffuse lobe
    if model.fresnel == "schlick":
        return (1.0 - f0) * t[..., 0:1]             # 1 - F = (1 - F0)(1 - F_c)
    if not model.metallic:
        return t[..., 2:3]
    # 1 - F = (1 - m)(1 - F_dielectric) + m (1 - base)(1 - F_c)
    return (1.0 - metallic) * t[..., 2:3] + metallic * (1.0 - base_color) * t[..., 0:1]


@functools.partial(jax.jit, static_argnames=("model",))
def shade_ibl(tables: IBLTables, n: Float[Array, "P 3"], v: Float[Array, "P 3"], base_color: Float[Array, "P 3"],
              metallic: Float[Array, "P 1"], roughness: Float[Array, "P 1"], model: Model = Model(),
              occlusion: Optional[Float[Array, "P 1"]] = None,
              factors: Optional[Float[Array, "P S"]] = None) -> Float[Array, "P 3"]:
    """Environment light reflected towards v by the split sum, linear RGB.

    diffuse = c_diff E(n)/π A_d(n·v, r) (A_d from `diffuse_lut`, matching the model's diffuse
    weight); specular = L_pre(R, r) (F0 scale + F90 bias), F90 = 1 (with ``fresnel="dielectric"``
    the dielectric part uses the exact-Fresnel albedo table instead), times
    `brdf.energy_compensation` when ``model.multiscatter``. ``occlusion`` multiplies both;
    ``factors`` (`OccludedTables.table`) multiply the diffuse term by k_d and the specular term by
    k_s at each point's roughness. Zero where n·v <= 0, as `brdf.evaluate`. metallic, roughness,
    occlusion may be (P, 1) or (P,).
    """
    col = lambda x: None if x is None else (x[..., None] if jnp.ndim(x) == jnp.ndim(base_color) - 1 else x)
    metallic, roughness, occlusion = col(jnp.asarray(metallic)), col(jnp.asarray(roughness)), col(occlusion)
    rough = brdf.clamp_inward(roughness[..., 0], 0.0, 1.0)
    nv_raw = dot3(n, v)
    nv = jnp.clip(nv_raw, 0.0, 1.0)
    to_env = lambda d: to_environment_frame(d, tables.world_up, tables.rotation_deg)
    k_d, k_s = (1.0, 1.0) if factors is None else factors_at(factors, rough)
    f0 = brdf.specular_f0(base_color, metallic, model)
    out = jnp.zeros(jnp.broadcast_shapes(jnp.shape(f0), nv.shape + (3,)), f0.dtype)
    if model.specular:
        r = 2 * nv_raw[..., None] * n - v
        if tables.specular_direction == "dominant":
            a = brdf.alpha_from_roughness(rough)[..., None]
            r = brdf.safe_normalize(r + (n - r) * a)
        dfg = lookup_brdf_lut(tables.lut, nv, rough)
        albedo = f0 * dfg[..., 0:1] + dfg[..., 1:2]
        if model.fresnel == "dielectric":        # F = mix(F_dielectric, Schlick(base_color), metallic)
            diel = lookup_table(tables.dielectric, nv, rough)
            albedo = diel if not model.metallic else (
                (1.0 - metallic) * diel + metallic * (base_color * dfg[..., 0:1] + dfg[..., 1:2]))
        spec = prefiltered_lookup(tables, to_env(r), rough) * albedo
        if model.multiscatter:
            spec = spec * brdf.energy_compensation(f0, dfg)
        out = out + spec * k_s
    if model.diffuse != "none":
        c_diff = brdf.diffuse_color(base_color, metallic, model)
        albedo = _diffuse_albedo(tables, nv, rough, base_color, metallic, f0, model)
        out = out + c_diff * albedo * irradiance_lookup(tables, to_env(n)) * k_d
    if occlusion is not None:
        out = out * occlusion
    return jnp.where((nv_raw > 0)[..., None], out, 0.0)
