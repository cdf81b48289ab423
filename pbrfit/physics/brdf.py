"""BRDF terms of the glTF 2.0 metallic-roughness model and the variants the field uses.

Every term is a pure ``jnp`` function of cosines and alpha (or k), broadcasting over leading
axes, finite in value and gradient over the closed domain: cosines in [0, 1] and roughness in
[0, 1], both ends included, in float32. Conventions:

- roughness is perceptual; ``alpha = roughness**2`` is computed only in `alpha_from_roughness`.
  A function that takes alpha names its argument ``alpha``.
- `evaluate` and `evaluate_cosines` return BRDF × cos(theta_l), linear RGB, shape (..., 3).

Sources: glTF 2.0 specification, Appendix B; Filament, "Physically Based Rendering in Filament"
(section 4.4); B. Walter et al., EGSR 2007; E. Heitz, JCGT 2014; B. Karis, SIGGRAPH 2013;
B. Burley, SIGGRAPH 2012; C. Schlick 1994.
"""

from __future__ import annotations

import functools
import math
from typing import Optional

import jax
import jax.numpy as jnp
from jax.scipy.special import erfc
from jaxtyping import Array, ArrayLike, Float

from .clamps import clamp_inward
from .model import Model

__all__ = [
    "MIN_ROUGHNESS",
    "MIN_ALPHA",
    "COS_MIN",
    "alpha_from_roughness",
    "safe_normalize",
    "v_plus_l_sq",
    "half_vector_cosines",
    "half_vector_sin2",
    "d_ggx",
    "d_beckmann",
    "lambda_ggx",
    "g1_smith_ggx",
    "g2_smith_ggx_correlated",
    "g2_smith_ggx_separable",
    "v_smith_ggx_correlated",
    "v_smith_ggx_separable",
    "lambda_beckmann",
    "g1_smith_beckmann",
    "v_smith_beckmann_correlated",
    "k_direct",
    "k_ibl",
    "g_schlick_ggx",
    "g2_schlick_ggx",
    "v_schlick_ggx",
    "f_schlick",
    "f_dielectric",
    "f0_from_ior",
    "diffuse_lambert",
    "diffuse_burley",
    "specular_f0",
    "diffuse_color",
    "energy_compensation",
    "specular_dv",
    "evaluate_cosines",
    "evaluate",
    "FLOORS",
]

# --- Named numerical floors ----------------------------------------------------------------------
#: Smallest perceptual roughness the model represents. Filament's float32 ("highp") minimum: below
#: it, D_GGX at n·h = 1 (= 1 / (pi alpha^2)) and its derivative in alpha (~ 1 / alpha^3) leave the
#: range where float32 products with V and light intensities stay accurate, and a point light's
#: highlight becomes narrower than any pixel can resolve. Roughness 0 is accepted and means this.
MIN_ROUGHNESS = 0.045
#: alpha = MIN_ROUGHNESS**2; the D terms also floor a directly passed alpha here (0/0 at alpha = 0).
MIN_ALPHA = MIN_ROUGHNESS * MIN_ROUGHNESS
#: Cosine floor inside terms that divide by n·v or n·l (V, Lambda, Beckmann's tan). Of the V
#: terms only the height-correlated ones diverge, as n·v and n·l both -> 0 (the separable and
#: Schlick forms stay below 1/alpha² and 1/(4k²)); `evaluate` multiplies by n·l and masks n·l <= 0 or n·v <= 0 to
#: exactly zero, so the floor only bounds the (unused) value at the horizon. Filament uses 1e-5
#: on n·v for the same reason; 1e-4 keeps V·(its derivative) inside float32 at MIN_ALPHA.
COS_MIN = 1e-4
#: Floor on |x|^2 when normalising a vector, so a zero vector yields a finite (zero) result and
#: the gradient of the norm stays finite (sqrt at 0 has an infinite derivative).
NORM2_MIN = 1e-12
#: Floor on k in the Schlick-GGX geometry term: at k = 0 and n·x = 0 the ratio is 0/0.
K_MIN = 0.5 * MIN_ALPHA

#: The floors as reported by ``pbrfit check-grads``.
FLOORS = {
    "MIN_ROUGHNESS": MIN_ROUGHNESS,
    "MIN_ALPHA": MIN_ALPHA,
    "COS_MIN": COS_MIN,
    "NORM2_MIN": NORM2_MIN,
    "K_MIN": K_MIN,
}

_INV_PI = 1.0 / math.pi


def alpha_from_roughness(roughness: Float[ArrayLike, "*batch"]) -> Float[Array, "*batch"]:
    """alpha = max(roughness, MIN_ROUGHNESS)^2 (glTF: alphaRoughness = perceptualRoughness^2);
    the floor by `clamp_inward` (derivative 1 at roughness = MIN_ROUGHNESS)."""
    r = clamp_inward(roughness, MIN_ROUGHNESS)
    return r * r


def _alpha(alpha):
    return clamp_inward(alpha, MIN_ALPHA)


def _cos(x):
    return clamp_inward(x, COS_MIN, 1.0)


def safe_normalize(x: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """x / max(|x|, 1e-6) (`NORM2_MIN`): a unit vector for |x| >= 1e-6, shorter below it and zero
    for a zero vector, with a finite gradient there."""
    x = jnp.asarray(x)
    n2 = jnp.sum(x * x, axis=-1, keepdims=True)
    return x * jnp.reciprocal(jnp.sqrt(jnp.maximum(n2, NORM2_MIN)))


def v_plus_l_sq(v: Float[ArrayLike, "*batch 3"], l: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch"]:
    """|v + l|² = Σ (v + l)², from the vectors: for `half_vector_cosines`.

    Written as three products (not ``jnp.sum``; see `pbrfit.lighting.environment.dot3`)."""
    v, l = jnp.asarray(v), jnp.asarray(l)
    s = v + l
    return s[..., 0] * s[..., 0] + s[..., 1] * s[..., 1] + s[..., 2] * s[..., 2]


def half_vector_sin2(n: Float[ArrayLike, "*batch 3"], v: Float[ArrayLike, "*batch 3"],
                     l: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch"]:
    """1 - (n·h)² for h = normalize(v + l), from the vectors: |n × (v + l)|² / |v + l|²
    (Lagrange's identity, as Filament §4.4.1 computes D_GGX in half precision).

    At a highlight's peak n·h rounds to 1 and 1 - (n·h)² loses its digits: in float32 at
    roughness 0.045, one unit in the last place of n·h moves D by about 6%, and D was off by up
    to 15% (65% at 89° from the normal) and its roughness derivative by up to 30%. The cross
    product keeps the relative precision. Pass it to the D terms (``sin2_h``). Where |v + l|² <
    `NORM2_MIN` (v -> -l, the half vector undefined) it is 1 - (n·h)² with n·h as
    `half_vector_cosines` floors it there, so the two stay consistent."""
    n, v, l = jnp.asarray(n), jnp.asarray(v), jnp.asarray(l)
    s = v + l
    n = jnp.broadcast_to(n, jnp.broadcast_shapes(n.shape, s.shape))
    c = jnp.cross(n, s)
    c2 = c[..., 0] * c[..., 0] + c[..., 1] * c[..., 1] + c[..., 2] * c[..., 2]
    s2 = v_plus_l_sq(v, l)
    wide = s2 >= NORM2_MIN
    nh = clamp_inward((n[..., 0] * s[..., 0] + n[..., 1] * s[..., 1] + n[..., 2] * s[..., 2]) / math.sqrt(NORM2_MIN),
                  0.0, 1.0)
    return jnp.where(wide, clamp_inward(c2 / jnp.where(wide, s2, 1.0), 0.0, 1.0), (1.0 - nh) * (1.0 + nh))


def half_vector_cosines(n_dot_v, n_dot_l, v_dot_l, v_plus_l_sq=None):
    """(n·h, v·h) for h = normalize(v + l), from the cosines of unit vectors.

    |v + l|² = 2 + 2 v·l; n·h = (n·v + n·l) / |v + l|; v·h = l·h = (1 + v·l) / |v + l| = |v + l|² / (2 |v + l|).
    Near a grazing mirror configuration (v -> -l) 2 + 2 v·l cancels: in float32, at n·v = n·l
    = 0.02 and roughness 0.1 the BRDF was off by up to 160%, and at n·v = n·l = 1e-4 v·l rounds
    to -1 and v·h to 0. Callers that hold the vectors pass ``v_plus_l_sq = Σ (v + l)²`` (`v_plus_l_sq`),
    which keeps its relative precision there; ``v_dot_l`` is then unused. At v = -l the half
    vector is undefined; both results are then 0 (the pair is masked anyway, since n·v and n·l
    cannot both be positive there).
    """
    if v_plus_l_sq is None:
        v_plus_l_sq = 2.0 + 2.0 * jnp.asarray(v_dot_l)
    length = jnp.sqrt(jnp.maximum(v_plus_l_sq, NORM2_MIN))
    n_dot_h = clamp_inward((n_dot_v + n_dot_l) / length, 0.0, 1.0)
    v_dot_h = clamp_inward(0.5 * v_plus_l_sq / length, 0.0, 1.0)
    return n_dot_h, v_dot_h


# --- Normal distribution functions ---------------------------------------------------------------
def _sin2(nh, sin2_h):
    """1 - (n·h)²: ``sin2_h`` when the caller has it from the vectors (`half_vector_sin2`), else
    (1 - n·h)(1 + n·h) from the cosine."""
    return (1.0 - nh) * (1.0 + nh) if sin2_h is None else clamp_inward(jnp.asarray(sin2_h), 0.0, 1.0)


def d_ggx(n_dot_h, alpha, sin2_h=None):
    """GGX / Trowbridge-Reitz normal distribution function.

    D(h) = χ⁺(n·h) alpha^2 / (pi ((n·h)^2 (alpha^2 - 1) + 1)^2)   (Walter et al. 2007, eq. 33; glTF B.3.2)

    The bracket is evaluated as (1 - (n·h)^2) + (n·h)^2 alpha^2, with 1 - (n·h)^2 from the
    vectors where the caller gives it (``sin2_h``, `half_vector_sin2`; Filament §4.4.1), else as
    (1 - n·h)(1 + n·h). alpha is floored at `MIN_ALPHA`; 0 where n·h <= 0 (χ⁺).
    Normalised so that ∫ D(h) (n·h) dω_h = 1 over the hemisphere.
    """
    a2 = jnp.square(_alpha(alpha))
    nh = clamp_inward(n_dot_h, 0.0, 1.0)
    front = jnp.asarray(n_dot_h) > 0.0
    b = jnp.where(front, _sin2(nh, sin2_h) + nh * nh * a2, 1.0)  # double where: b may be 0 behind
    return jnp.where(front, a2 * _INV_PI / (b * b), 0.0)


def d_beckmann(n_dot_h, alpha, sin2_h=None):
    """Beckmann normal distribution function.

    D(h) = χ⁺(n·h) exp(-tan^2(theta_h) / alpha^2) / (pi alpha^2 cos^4(theta_h))   (Walter et al. 2007, eq. 25)

    n·h is floored at `COS_MIN` (tan^2 -> inf; D -> 0 there, as the formula's limit). The
    1 / cos^4 factor is folded into the exponent: at grazing n·h and small alpha, alpha^2 cos^4
    underflows float32 (~1e-22, squared ~1e-44 in the reverse pass) and the quotient's gradient
    would be 0 · inf = NaN; exp(-tan^2/alpha^2 - 2 log cos^2) / (pi alpha^2) has none.
    tan^2 = (1 - (n·h)^2) / (n·h)^2, the numerator from the vectors where given (``sin2_h``,
    as `d_ggx`).
    """
    a2 = jnp.square(_alpha(alpha))
    nh = _cos(n_dot_h)
    nh2 = nh * nh
    tan2 = _sin2(nh, sin2_h) / nh2
    return jnp.where(jnp.asarray(n_dot_h) > 0.0, jnp.exp(-tan2 / a2 - 2.0 * jnp.log(nh2)) * _INV_PI / a2, 0.0)


# --- Smith masking-shadowing for GGX -----------------------------------------------------------
def _ggx_root(n_dot_x, alpha):
    """sqrt(alpha^2 + (1 - alpha^2)(n·x)^2) = n·x sqrt(1 + alpha^2 tan^2 theta); > 0 for alpha > 0."""
    a2 = jnp.square(_alpha(alpha))
    c = clamp_inward(n_dot_x, 0.0, 1.0)
    return jnp.sqrt(a2 + (1.0 - a2) * c * c)


def lambda_ggx(n_dot_x, alpha):
    """Smith Lambda for GGX: Λ(x) = (-1 + sqrt(1 + alpha^2 tan^2 theta_x)) / 2.

    Walter et al. 2007, eq. 34 (via Heitz 2014, eq. 72). Written without the cancellation of
    -1 + sqrt(...) at small alpha tan: Λ = t / (2 (1 + sqrt(1 + t))), t = alpha^2 tan^2 =
    alpha^2 (1 - (n·x)^2) / (n·x)^2, with n·x floored at `COS_MIN`; Λ -> inf at grazing, so the
    value there is large but finite.
    """
    c = _cos(n_dot_x)
    t = jnp.square(_alpha(alpha)) * (1.0 - c) * (1.0 + c) / (c * c)
    return 0.5 * t / (1.0 + jnp.sqrt(1.0 + t))


def g1_smith_ggx(n_dot_x, alpha):
    """Exact Smith G1 for GGX: G1 = 1 / (1 + Λ) = 2 n·x / (n·x + sqrt(alpha^2 + (1 - alpha^2)(n·x)^2)).

    Walter et al. 2007, eq. 34. The second form has no division by n·x: G1(0) = 0 exactly.
    """
    c = clamp_inward(n_dot_x, 0.0, 1.0)
    return 2.0 * c / (c + _ggx_root(c, alpha))


def g2_smith_ggx_correlated(n_dot_v, n_dot_l, alpha):
    """Height-correlated Smith G2 for GGX: G2 = 1 / (1 + Λ(v) + Λ(l)).

    Heitz 2014, eq. 99. Written without divisions by the cosines:
    G2 = 2 n·v n·l / (n·l sqrt(alpha^2 + (1 - alpha^2)(n·v)^2) + n·v sqrt(alpha^2 + (1 - alpha^2)(n·l)^2)),
    times χ⁺(n·v) χ⁺(n·l): 0 at and below the horizon (the cosines' floor would leave it above 0).
    """
    nv = _cos(n_dot_v)
    nl = _cos(n_dot_l)
    g2 = 2.0 * nv * nl / (nl * _ggx_root(nv, alpha) + nv * _ggx_root(nl, alpha))
    return jnp.where((jnp.asarray(n_dot_v) > 0.0) & (jnp.asarray(n_dot_l) > 0.0), g2, 0.0)


def g2_smith_ggx_separable(n_dot_v, n_dot_l, alpha):
    """Uncorrelated (separable) Smith G2 for GGX: G1(v) G1(l) (Walter et al. 2007, eq. 23 & 34)."""
    return g1_smith_ggx(n_dot_v, alpha) * g1_smith_ggx(n_dot_l, alpha)


def v_smith_ggx_correlated(n_dot_v, n_dot_l, alpha):
    """Visibility V = G2 / (4 n·v n·l) for the height-correlated Smith GGX term.

    V = 0.5 / (n·l sqrt(n·v^2 (1 - alpha^2) + alpha^2) + n·v sqrt(n·l^2 (1 - alpha^2) + alpha^2))
    glTF 2.0 Appendix B.3.2 (V_GGX; alpha^2 inside the roots, alpha = roughness^2) and Filament's
    V_SmithGGXCorrelated. Cosines floored at `COS_MIN`, so V is bounded at the horizon.
    """
    nv = _cos(n_dot_v)
    nl = _cos(n_dot_l)
    return 0.5 / (nl * _ggx_root(nv, alpha) + nv * _ggx_root(nl, alpha))


def v_smith_ggx_separable(n_dot_v, n_dot_l, alpha):
    """V = G1(v) G1(l) / (4 n·v n·l) = 1 / ((n·v + root_v)(n·l + root_l)), roots as in `g1_smith_ggx`."""
    nv = clamp_inward(n_dot_v, 0.0, 1.0)
    nl = clamp_inward(n_dot_l, 0.0, 1.0)
    return 1.0 / ((nv + _ggx_root(nv, alpha)) * (nl + _ggx_root(nl, alpha)))


# --- Smith masking-shadowing for Beckmann ------------------------------------------------------
#: Above this a = 1 / (alpha tan theta) Beckmann's Λ is below 1e-45, 0 in float32 and float64
#: alike to the precision that matters; a is capped there (Λ's terms are 0 · inf beyond).
BECKMANN_A_MAX = 10.0


def lambda_beckmann(n_dot_x, alpha):
    """Smith Lambda for Beckmann: Λ(a) = (erf(a) - 1) / 2 + exp(-a²) / (2 a sqrt(pi)),
    a = 1 / (alpha tan theta_x) = n·x / (alpha sqrt(1 - (n·x)²)).

    Walter et al. 2007, eq. 26 (the exact form; eq. 27 is a rational fit, not used here);
    Heitz 2014, eq. 80. Written with erfc (no cancellation in erf(a) - 1). n·x is floored at `COS_MIN`
    (Λ -> inf at grazing: large but finite there) and a capped at `BECKMANN_A_MAX` (Λ = 0).
    """
    c = _cos(n_dot_x)
    sin = jnp.sqrt(jnp.maximum((1.0 - c) * (1.0 + c), NORM2_MIN))
    a = jnp.minimum(c / (_alpha(alpha) * sin), BECKMANN_A_MAX)
    return 0.5 * (jnp.exp(-a * a) / (a * math.sqrt(math.pi)) - erfc(a))


def g1_smith_beckmann(n_dot_x, alpha):
    """Exact Smith G1 for Beckmann: χ⁺(n·x) / (1 + Λ) with `lambda_beckmann` (Walter et al. 2007,
    eq. 26): 0 at and below the horizon (the cosine's floor would leave it above 0)."""
    return jnp.where(jnp.asarray(n_dot_x) > 0.0, 1.0 / (1.0 + lambda_beckmann(n_dot_x, alpha)), 0.0)


def v_smith_beckmann_correlated(n_dot_v, n_dot_l, alpha):
    """V = G2 / (4 n·v n·l) with the height-correlated Smith G2 = 1 / (1 + Λ(v) + Λ(l)) for
    Beckmann (Heitz 2014, eq. 99, with `lambda_beckmann`). Cosines floored at `COS_MIN`."""
    nv = _cos(n_dot_v)
    nl = _cos(n_dot_l)
    g2 = 1.0 / (1.0 + lambda_beckmann(nv, alpha) + lambda_beckmann(nl, alpha))
    return g2 / (4.0 * nv * nl)


def k_direct(roughness):
    """Schlick-GGX k for punctual lights: k = (roughness + 1)^2 / 8 (Karis 2013, "remapping")."""
    return jnp.square(jnp.asarray(roughness) + 1.0) / 8.0


def k_ibl(alpha):
    """Schlick-GGX k for image-based lighting: k = alpha / 2 (Karis 2013)."""
    return 0.5 * jnp.asarray(alpha)


def g_schlick_ggx(n_dot_x, k):
    """Schlick-GGX G1: n·x / (n·x (1 - k) + k) (Schlick 1994, as used by Karis 2013). k >= `K_MIN`."""
    c = clamp_inward(n_dot_x, 0.0, 1.0)
    k = clamp_inward(k, K_MIN)
    return c / (c * (1.0 - k) + k)


def g2_schlick_ggx(n_dot_v, n_dot_l, k):
    """Separable Smith product of Schlick-GGX terms: G1(v) G1(l) (Karis 2013)."""
    return g_schlick_ggx(n_dot_v, k) * g_schlick_ggx(n_dot_l, k)


def v_schlick_ggx(n_dot_v, n_dot_l, k):
    """V = G2 / (4 n·v n·l) = 1 / (4 (n·v (1 - k) + k)(n·l (1 - k) + k)) for the Schlick-GGX product."""
    nv = clamp_inward(n_dot_v, 0.0, 1.0)
    nl = clamp_inward(n_dot_l, 0.0, 1.0)
    k = clamp_inward(k, K_MIN)
    return 0.25 / ((nv * (1.0 - k) + k) * (nl * (1.0 - k) + k))


# --- Fresnel -----------------------------------------------------------------------------------
def f_schlick(v_dot_h, f0, f90=1.0):
    """Schlick's Fresnel: F = f0 + (f90 - f0)(1 - v·h)^5 (Schlick 1994; glTF B.3.4).

    The fifth power is written as products, so its derivative at v·h = 1 is exactly 0.
    Broadcasts a scalar cosine against an RGB f0 when given `v_dot_h[..., None]`.
    """
    m = 1.0 - clamp_inward(v_dot_h, 0.0, 1.0)
    m2 = m * m
    return f0 + (f90 - f0) * (m2 * m2 * m)


def f_dielectric(cos_theta, ior):
    """Exact unpolarised Fresnel reflectance of a dielectric, light arriving from outside (eta = ior).

    With g = sqrt(eta^2 - 1 + c^2):
    F = 1/2 ((g - c)/(g + c))^2 (1 + ((c (g + c) - 1) / (c (g - c) + 1))^2)   (Walter et al. 2007, eq. 22)
    g^2 is floored at `NORM2_MIN` (it reaches 0 only for eta = 1 at grazing incidence).
    """
    c = clamp_inward(cos_theta, 0.0, 1.0)
    g = jnp.sqrt(jnp.maximum(jnp.square(ior) - 1.0 + c * c, NORM2_MIN))
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


def f0_from_ior(ior):
    """Normal-incidence reflectance f0 = ((ior - 1) / (ior + 1))^2; 0.04 at ior 1.5 (glTF)."""
    return jnp.square((jnp.asarray(ior) - 1.0) / (jnp.asarray(ior) + 1.0))


# --- Diffuse lobes -----------------------------------------------------------------------------
def diffuse_lambert(n_dot_v, n_dot_l, l_dot_h, roughness):
    """Lambert: f_d = 1 / pi (times the diffuse color). glTF B.3.5; Filament Fd_Lambert.

    Takes the same arguments as `diffuse_burley` so the lobes are interchangeable; it depends
    on none of them.
    """
    shape = jnp.broadcast_shapes(jnp.shape(n_dot_v), jnp.shape(n_dot_l), jnp.shape(l_dot_h), jnp.shape(roughness))
    return jnp.full(shape, _INV_PI, dtype=jnp.result_type(n_dot_v, float))


def diffuse_burley(n_dot_v, n_dot_l, l_dot_h, roughness):
    """Burley's (Disney) diffuse: f_d = (1/pi) F(n·l) F(n·v), F(x) = 1 + (F_D90 - 1)(1 - x)^5,
    F_D90 = 1/2 + 2 roughness (l·h)^2.

    Burley 2012, section 5.3, with `roughness` perceptual as in Disney's parameterisation
    (Filament's Fd_Burley passes alpha instead). Times the diffuse color.
    """
    f90 = 0.5 + 2.0 * jnp.asarray(roughness) * jnp.square(clamp_inward(l_dot_h, 0.0, 1.0))
    return _INV_PI * f_schlick(n_dot_l, 1.0, f90) * f_schlick(n_dot_v, 1.0, f90)


_DIFFUSE = {"lambert": diffuse_lambert, "burley": diffuse_burley}


# --- Composition -----------------------------------------------------------------------------------
def specular_f0(base_color, metallic, model: Model = Model()):
    """f0 = mix(f0_dielectric, base_color, metallic), f0_dielectric = ((ior - 1)/(ior + 1))^2 (glTF B.3.5)."""
    f0_d = ((model.ior - 1.0) / (model.ior + 1.0)) ** 2  # static: f0_from_ior on a Python float
    if not model.metallic:
        return jnp.full(jnp.shape(base_color), f0_d, dtype=jnp.result_type(base_color, float))
    return f0_d + (base_color - f0_d) * metallic


def diffuse_color(base_color, metallic, model: Model = Model()):
    """c_diff = mix(base_color, 0, metallic) = (1 - metallic) base_color (glTF B.3.5)."""
    if not model.metallic:
        return jnp.asarray(base_color)
    return base_color * (1.0 - metallic)


def energy_compensation(f0, dfg):
    """Multiple-scattering compensation factor for the specular lobe.

    1 + f0 (1 / (scale + bias) - 1), with (scale, bias) = dfg[..., 0:2] the split-sum DFG terms at
    (n·v, roughness), so scale + bias is the single-scattering directional albedo for f0 = 1.
    Kulla & Conty 2017; Filament section 4.7.2.
    """
    e = jnp.maximum(dfg[..., 0:1] + dfg[..., 1:2], COS_MIN)
    return 1.0 + f0 * (1.0 / e - 1.0)


def _geometry(model: Model, n_dot_v, n_dot_l, roughness, alpha):
    if model.geometry == "smith_ggx_correlated":
        return v_smith_ggx_correlated(n_dot_v, n_dot_l, alpha)
    if model.geometry == "smith_ggx_separable":
        return v_smith_ggx_separable(n_dot_v, n_dot_l, alpha)
    if model.geometry == "smith_beckmann_correlated":
        return v_smith_beckmann_correlated(n_dot_v, n_dot_l, alpha)
    if model.geometry == "schlick_ggx_direct":
        return v_schlick_ggx(n_dot_v, n_dot_l, k_direct(clamp_inward(roughness, MIN_ROUGHNESS)))
    return v_schlick_ggx(n_dot_v, n_dot_l, k_ibl(alpha))


def specular_dv(model: Model, n_dot_v, n_dot_l, n_dot_h, roughness, sin2_h=None):
    """D V of the model's specular lobe (the microfacet BRDF without Fresnel), at cosines n·v,
    n·l already clipped to [0, 1] and perceptual roughness; D = `d_ggx` or `d_beckmann` (with
    1 - (n·h)² from the vectors where given, ``sin2_h``), V as `model.geometry` (see
    `evaluate_cosines`)."""
    alpha = alpha_from_roughness(roughness)
    d = d_ggx(n_dot_h, alpha, sin2_h) if model.distribution == "ggx" else d_beckmann(n_dot_h, alpha, sin2_h)
    return d * _geometry(model, n_dot_v, n_dot_l, roughness, alpha)


def _fresnel(model: Model, v_dot_h, base_color, metallic, f0):
    vh = v_dot_h[..., None]
    if model.fresnel == "schlick":
        return f_schlick(vh, f0)
    f_d = f_dielectric(vh, model.ior)
    if not model.metallic:
        return jnp.broadcast_to(f_d, jnp.shape(f0))
    return f_d + (f_schlick(vh, base_color) - f_d) * metallic


def per_point(x: Float[ArrayLike, "*batch"] | Float[ArrayLike, "*batch 1"], rank: Optional[int] = None,
              name: str = "value") -> Float[Array, "*batch 1"]:
    """A per-point scalar (metallic, roughness) with the trailing axis of 1 that broadcasts
    against RGB.

    With ``rank`` (the batch's number of axes, as `evaluate` knows it from its vectors): an
    array of ``rank + 1`` axes ending in 1 has it already; any other gains it (and broadcasts
    against the batch: a roughness sweep at one geometry gives one row per value). Without
    (`evaluate_cosines`, whose cosines may carry leading axes the material broadcasts against):
    a scalar gains it, and any other array must end in it; (B,) is refused rather than
    broadcast across RGB."""
    x = jnp.asarray(x)
    if rank is not None:
        return x if (x.ndim == rank + 1 and x.shape[-1] == 1) else x[..., None]
    if x.ndim == 0:
        return x[..., None]
    if x.shape[-1] == 1:
        return x
    raise ValueError(f"{name} must hold one value per point, shape (*batch, 1); got shape {x.shape}")


@functools.partial(jax.jit, static_argnames="model")
def evaluate_cosines(
    n_dot_v: Float[ArrayLike, "*batch"],
    n_dot_l: Float[ArrayLike, "*batch"],
    n_dot_h: Float[ArrayLike, "*batch"],
    v_dot_h: Float[ArrayLike, "*batch"],
    base_color: Float[ArrayLike, "*batch 3"],
    metallic: Float[ArrayLike, "*batch 1"],
    roughness: Float[ArrayLike, "*batch 1"],
    model: Model = Model(),
    dfg: Float[ArrayLike, "*batch 2"] | None = None,
    sin2_h: Float[ArrayLike, "*batch"] | None = None,
) -> Float[Array, "*batch 3"]:
    """BRDF × n·l from cosines, linear RGB (glTF 2.0 Appendix B, "simplified" metallic-roughness form).

    f = (1 - F) (1 - metallic) base_color / pi + F D V,   F = Schlick(v·h, f0),
    f0 = mix(0.04, base_color, metallic), D and V as chosen by `model` (default GGX and
    height-correlated Smith). Burley's diffuse replaces (1 - F)/pi by its own factors (Disney
    2012). `dfg` (split-sum scale and bias at (n·v, roughness)) is required when
    ``model.multiscatter``. Zero where n·l <= 0 or n·v <= 0. ``sin2_h``: 1 - (n·h)² from the
    vectors (`half_vector_sin2`), which the D terms need for float32 accuracy near a highlight's
    peak at low roughness; without it, from ``n_dot_h``.

    metallic and roughness hold one value per point with a trailing axis of 1 that broadcasts
    against RGB, (*batch, 1), or are scalars (`per_point`; `evaluate` takes (*batch) as well).

    Energy: Lambert and the single-scattering specular lobe each conserve energy alone (white
    Lambert integrates to 1, the specular lobe to at most 1); Burley's diffuse does not (a white
    Burley lobe alone integrates to 1.04 at n·v = 1 and 1.15 at n·v = 0.3, roughness 1, as
    Disney's model does). glTF's (1 - F(v·h)) diffuse weighting does not
    remove what the specular lobe's masking loses, so a white dielectric reflects more than
    it receives at grazing views (∫ f cos dω ≈ 1.03 at n·v = 0.5 and 1.33 at n·v = 0.05,
    roughness 0.3). That is the glTF model as viewers render it, kept as the default so that
    fitted maps look in a glTF viewer as they did in the fit; tests pin the excess.
    """
    n_dot_v = jnp.asarray(n_dot_v)
    n_dot_l = jnp.asarray(n_dot_l)
    base_color = jnp.asarray(base_color)
    if base_color.ndim == 0 or base_color.shape[-1] != 3:
        raise ValueError(f"base_color must be linear RGB, shape (*batch, 3); got shape {base_color.shape}")
    metallic = per_point(metallic, name="metallic")
    roughness = clamp_inward(per_point(roughness, name="roughness"), 0.0, 1.0)
    lit = (n_dot_v > 0.0) & (n_dot_l > 0.0)
    nv = clamp_inward(n_dot_v, 0.0, 1.0)
    nl = clamp_inward(n_dot_l, 0.0, 1.0)
    rough = roughness[..., 0]

    f0 = specular_f0(base_color, metallic, model)
    fresnel = _fresnel(model, jnp.asarray(v_dot_h), base_color, metallic, f0)
    out = jnp.zeros(jnp.broadcast_shapes(jnp.shape(f0), jnp.shape(nv) + (1,)), dtype=f0.dtype)

    if model.specular:
        spec = fresnel * specular_dv(model, nv, nl, n_dot_h, rough, sin2_h)[..., None]
        if model.multiscatter:
            if dfg is None:
                raise ValueError("Model(multiscatter=True) needs dfg (split-sum scale, bias at n·v, roughness)")
            spec = spec * energy_compensation(f0, jnp.asarray(dfg))
        out = out + spec

    if model.diffuse != "none":
        c_diff = diffuse_color(base_color, metallic, model)
        l_dot_h = v_dot_h  # h bisects v and l
        fd = _DIFFUSE[model.diffuse](nv, nl, l_dot_h, rough)[..., None]
        weight = (1.0 - fresnel) if (model.diffuse == "lambert" and model.specular) else 1.0
        out = out + weight * c_diff * fd

    return jnp.where(lit[..., None], out * nl[..., None], 0.0)


@functools.partial(jax.jit, static_argnames="model")
def evaluate(
    n: Float[ArrayLike, "*batch 3"],
    v: Float[ArrayLike, "*batch 3"],
    l: Float[ArrayLike, "*batch 3"],
    base_color: Float[ArrayLike, "*batch 3"],
    metallic: Float[ArrayLike, "*batch"] | Float[ArrayLike, "*batch 1"],
    roughness: Float[ArrayLike, "*batch"] | Float[ArrayLike, "*batch 1"],
    model: Model = Model(),
    dfg: Float[ArrayLike, "*batch 2"] | None = None,
) -> Float[Array, "*batch 3"]:
    """BRDF × n·l for unit vectors n (normal), v (to the viewer), l (to the light); linear RGB.

    metallic and roughness hold one value per point, without a trailing axis (*batch) or with
    one of 1 (*batch, 1), as `evaluate_cosines` takes them (`per_point`). See `evaluate_cosines`.
    """
    n, v, l = (jnp.asarray(x) for x in (n, v, l))
    for name, x in (("n", n), ("v", v), ("l", l), ("base_color", base_color)):
        if jnp.ndim(x) == 0 or jnp.shape(x)[-1] != 3:
            raise ValueError(f"{name} must end in an axis of 3 (*batch, 3); got shape {jnp.shape(x)}")
    rank = max(n.ndim, v.ndim, l.ndim, jnp.ndim(base_color)) - 1
    n_dot_v = jnp.sum(n * v, axis=-1)
    n_dot_l = jnp.sum(n * l, axis=-1)
    n_dot_h, v_dot_h = half_vector_cosines(n_dot_v, n_dot_l, None, v_plus_l_sq(v, l))
    return evaluate_cosines(
        n_dot_v,
        n_dot_l,
        n_dot_h,
        v_dot_h,
        base_color,
        per_point(metallic, rank, "metallic"),
        per_point(roughness, rank, "roughness"),
        model,
        dfg,
        half_vector_sin2(n, v, l),
    )
