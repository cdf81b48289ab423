"""What `pbrfit check-grads` differentiates: every public BRDF term, `brdf.evaluate_cosines`
under each `Model` variant, `brdf.evaluate`, and the sRGB curves, exposure and tone maps of
`color`, each as a `Spec`: a function of a vector of scalar inputs, its grid of points, and its
kinks (clamps, branch switches, the ends of its domains) per input, where no derivative exists
and finite differences must not reach. The checks themselves: `pbrfit.checks.gradcheck`."""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Callable, Optional

import jax.numpy as jnp
import numpy as np

from ..physics import brdf
from ..physics import color
from .finite_differences import KINK_MARGIN
from ..physics.model import Model

__all__ = ["Spec", "all_specs", "product_grid", "model_label", "MODEL_VARIANTS", "COSINES", "ALPHAS", "ROUGHNESS"]

#: Fixed weights that turn an RGB (or other vector) output into the scalar that is differentiated;
#: unequal so that a wrong channel cannot cancel.
_RGB_WEIGHTS = (0.6, 0.3, 0.1)
#: A grey base color is a scalar input times this tint (three distinct channels).
_TINT = (1.0, 0.7, 0.4)


@dataclasses.dataclass(frozen=True)
class Spec:
    term: str
    fn: Callable  # (k,) float64 -> scalar
    names: tuple
    grid: np.ndarray  # (N, k)
    kinks: tuple  # per input: the input values where the function has a kink
    skip: Optional[Callable] = None  # (N, k) -> (N,) bool: extra, output-dependent kinks


# --- Grids -------------------------------------------------------------------------------------
COSINES = (0.05, 0.2, 0.5, 0.8, 0.95)
ALPHAS = (0.005, 0.01, 0.1, 0.3, 0.7)
ROUGHNESS = (0.06, 0.1, 0.3, 0.6, 0.9)
_COS_KINKS = (0.0, brdf.COS_MIN, 1.0)
_ALPHA_KINKS = (brdf.MIN_ALPHA,)
_ROUGH_KINKS = (0.0, brdf.MIN_ROUGHNESS, 1.0)


def product_grid(*axes) -> np.ndarray:
    return np.array(list(itertools.product(*axes)), dtype=np.float64)


def _weighted(y):
    y = jnp.asarray(y)
    if y.ndim == 0:
        return y
    return jnp.sum(y * jnp.asarray(_RGB_WEIGHTS[: y.shape[-1]], dtype=y.dtype))


def _scalar_terms() -> list:
    """The public terms of `brdf`, each as a function of a vector of its scalar inputs."""
    c, a, r = COSINES, ALPHAS, ROUGHNESS
    ck, ak, rk = _COS_KINKS, _ALPHA_KINKS, _ROUGH_KINKS
    cos3 = (0.2, 0.5, 0.9)
    specs = [
        Spec("alpha_from_roughness", lambda x: brdf.alpha_from_roughness(x[0]), ("roughness",), product_grid(r), (rk,)),
        Spec("d_ggx", lambda x: brdf.d_ggx(x[0], x[1]), ("n·h", "alpha"), product_grid(c, a), (ck, ak)),
        Spec("d_beckmann", lambda x: brdf.d_beckmann(x[0], x[1]), ("n·h", "alpha"), product_grid(c, a), (ck, ak)),
        Spec("lambda_ggx", lambda x: brdf.lambda_ggx(x[0], x[1]), ("n·x", "alpha"), product_grid(c, a), (ck, ak)),
        Spec("g1_smith_ggx", lambda x: brdf.g1_smith_ggx(x[0], x[1]), ("n·x", "alpha"), product_grid(c, a), (ck, ak)),
        Spec("lambda_beckmann", lambda x: brdf.lambda_beckmann(x[0], x[1]), ("n·x", "alpha"), product_grid(c, a), (ck, ak),
              skip=_beckmann_cap_skip),
        Spec("g1_smith_beckmann", lambda x: brdf.g1_smith_beckmann(x[0], x[1]), ("n·x", "alpha"), product_grid(c, a),
              (ck, ak), skip=_beckmann_cap_skip),
        Spec("v_smith_beckmann_correlated", lambda x: brdf.v_smith_beckmann_correlated(x[0], x[1], x[2]),
              ("n·v", "n·l", "alpha"), product_grid(c, c, a), (ck, ck, ak),
              skip=lambda p: _beckmann_cap_skip(p[:, [0, 2]]) | _beckmann_cap_skip(p[:, [1, 2]])),
    ]
    for name in ("g2_smith_ggx_correlated", "g2_smith_ggx_separable", "v_smith_ggx_correlated", "v_smith_ggx_separable"):
        fn = getattr(brdf, name)
        specs.append(Spec(name, lambda x, fn=fn: fn(x[0], x[1], x[2]), ("n·v", "n·l", "alpha"), product_grid(c, c, a), (ck, ck, ak)))
    k_grid = (0.01, 0.1, 0.3, 0.6)
    k_kinks = (brdf.K_MIN,)
    specs += [
        Spec("k_direct", lambda x: brdf.k_direct(x[0]), ("roughness",), product_grid(r), ((),)),
        Spec("k_ibl", lambda x: brdf.k_ibl(x[0]), ("alpha",), product_grid(a), ((),)),
        Spec("g_schlick_ggx", lambda x: brdf.g_schlick_ggx(x[0], x[1]), ("n·x", "k"), product_grid(c, k_grid), (ck, k_kinks)),
        Spec("g2_schlick_ggx", lambda x: brdf.g2_schlick_ggx(x[0], x[1], x[2]), ("n·v", "n·l", "k"),
              product_grid(c, c, k_grid), (ck, ck, k_kinks)),
        Spec("v_schlick_ggx", lambda x: brdf.v_schlick_ggx(x[0], x[1], x[2]), ("n·v", "n·l", "k"),
              product_grid(c, c, k_grid), (ck, ck, k_kinks)),
        Spec("f_schlick", lambda x: brdf.f_schlick(x[0], x[1], x[2]), ("v·h", "f0", "f90"),
              product_grid(c, (0.04, 0.5, 0.9), (0.5, 1.0)), (ck, (), ())),
        Spec("f_dielectric", lambda x: brdf.f_dielectric(x[0], x[1]), ("cos_theta", "ior"),
              product_grid(c, (1.2, 1.5, 2.4)), (ck, ())),
        Spec("f0_from_ior", lambda x: brdf.f0_from_ior(x[0]), ("ior",), product_grid((1.1, 1.5, 2.0, 3.0)), ((),)),
        Spec("diffuse_lambert", lambda x: brdf.diffuse_lambert(x[0], x[1], x[2], x[3]), ("n·v", "n·l", "l·h", "roughness"),
              product_grid(cos3, cos3, cos3, r), (ck, ck, ck, ())),
        Spec("diffuse_burley", lambda x: brdf.diffuse_burley(x[0], x[1], x[2], x[3]), ("n·v", "n·l", "l·h", "roughness"),
              product_grid(cos3, cos3, cos3, r), (ck, ck, ck, ())),
        Spec("half_vector_cosines", lambda x: _weighted(jnp.stack(brdf.half_vector_cosines(x[0], x[1], x[2]))),
              ("n·v", "n·l", "v·l"), product_grid((0.3, 0.6, 0.9), (0.3, 0.6, 0.9), (-0.5, 0.0, 0.5, 0.9)), ((), (), (-1.0,)),
              skip=_half_vector_skip),
        Spec("v_plus_l_sq", lambda x: brdf.v_plus_l_sq(x[:3], x[3:]), ("v_x", "v_y", "v_z", "l_x", "l_y", "l_z"),
              product_grid((-0.6, 0.3), (0.2, 0.8), (0.1, 0.7), (-0.5, 0.4), (-0.3, 0.6), (0.2, 0.9)), ((),) * 6),
        Spec("half_vector_sin2", lambda x: brdf.half_vector_sin2(x[:3] / jnp.linalg.norm(x[:3]), x[3:6], x[6:]),
              ("n_x", "n_y", "n_z", "v_x", "v_y", "v_z", "l_x", "l_y", "l_z"),
              product_grid((0.1, 0.4), (0.2,), (0.9,), (-0.6, 0.3), (0.2,), (0.7,), (0.5,), (-0.3, 0.6), (0.6,)), ((),) * 9),
        Spec("safe_normalize", lambda x: _weighted(brdf.safe_normalize(x)), ("x", "y", "z"),
              product_grid((-0.7, 0.2, 1.5), (-0.3, 0.4), (0.1, 0.9)), ((), (), ())),
        Spec("specular_dv", lambda x: brdf.specular_dv(Model(), x[0], x[1], x[2], x[3]), ("n·v", "n·l", "n·h", "roughness"),
              product_grid(cos3, cos3, cos3, r), (ck, ck, ck, rk)),
        Spec("specular_f0", lambda x: _weighted(brdf.specular_f0(x[0] * jnp.asarray(_TINT), x[1])),
              ("base_color", "metallic"), product_grid((0.2, 0.8), (0.0, 0.4, 1.0)), ((), ())),
        Spec("diffuse_color", lambda x: _weighted(brdf.diffuse_color(x[0] * jnp.asarray(_TINT), x[1])),
              ("base_color", "metallic"), product_grid((0.2, 0.8), (0.0, 0.4, 1.0)), ((), ())),
        Spec("energy_compensation",
              lambda x: _weighted(brdf.energy_compensation(x[0] * jnp.asarray(_TINT), jnp.stack([x[1], x[2]]))),
              ("f0", "dfg_scale", "dfg_bias"), product_grid((0.04, 0.5, 1.0), (0.3, 0.7, 0.95), (0.0, 0.02, 0.05)), ((), (), ())),
    ]
    return specs


def _beckmann_cap_skip(p):
    # Λ_Beckmann's a = n·x / (alpha sin) is capped at BECKMANN_A_MAX. Past a = 4, Λ < 1e-8 is
    # exp(-a²)'s tail, whose higher derivatives in alpha outgrow any central difference step:
    # the check is left to points where Λ matters.
    c, a = p[:, 0], np.maximum(p[:, 1], brdf.MIN_ALPHA)
    x = c / (a * np.sqrt(np.maximum(1.0 - c * c, 1e-300)))
    return x > 4.0


def _half_vector_skip(p):
    # n·h and v·h are clipped to [0, 1]: skip where either (unclipped) reaches within a margin of 1.
    nv, nl, vl = p[:, 0], p[:, 1], p[:, 2]
    length = np.sqrt(2.0 + 2.0 * vl)
    nh, vh = (nv + nl) / length, (1.0 + vl) / length
    return (np.abs(nh - 1.0) < 10 * KINK_MARGIN) | (np.abs(vh - 1.0) < 10 * KINK_MARGIN)


#: One Model per variant value (each field's non-default values appear at least once).
MODEL_VARIANTS = (
    Model(),
    Model(distribution="beckmann"),
    Model(distribution="beckmann", geometry="smith_beckmann_correlated"),
    Model(geometry="smith_ggx_separable"),
    Model(geometry="schlick_ggx_direct"),
    Model(geometry="schlick_ggx_ibl"),
    Model(fresnel="dielectric"),
    Model(fresnel="dielectric", metallic=False),
    Model(metallic=False),
    Model(diffuse="burley"),
    Model(diffuse="none"),
    Model(specular=False),
    Model(multiscatter=True),
)

#: (scale, bias) used as the split-sum DFG input of the multiscatter model (any plausible value).
_DFG = (0.7, 0.05)


def model_label(model: Model) -> str:
    """The fields of `model` that differ from the default, as ``k=v,...`` (``default`` if none)."""
    d = Model().describe()
    changed = [f"{k}={v}" for k, v in model.describe().items() if d[k] != v]
    return ",".join(changed) or "default"


def _evaluate_cosines_spec(model: Model) -> Spec:
    def fn(x):
        base = x[4] * jnp.asarray(_TINT, dtype=x.dtype)
        dfg = jnp.asarray(_DFG, dtype=x.dtype) if model.multiscatter else None
        out = brdf.evaluate_cosines(x[0], x[1], x[2], x[3], base, x[5][None], x[6][None], model, dfg)
        return _weighted(out)

    # 216 points: the composition is what is checked here (each term has its own denser grid).
    grid = product_grid((0.2, 0.7), (0.2, 0.7), (0.5, 0.9, 0.98), (0.3, 0.9), (0.7,), (0.0, 0.5, 1.0), (0.1, 0.4, 0.9))
    kinks = (_COS_KINKS, _COS_KINKS, _COS_KINKS, _COS_KINKS, (), (), _ROUGH_KINKS)
    return Spec(f"evaluate_cosines[{model_label(model)}]", fn,
                 ("n·v", "n·l", "n·h", "v·h", "base_color", "metallic", "roughness"), grid, kinks)


def _evaluate_spec() -> Spec:
    """`evaluate` from directions: v and l at polar angles θv, θl, azimuth φ between them, n = +z."""

    def fn(x):
        tv, tl, phi = x[0], x[1], x[2]
        n = jnp.array([0.0, 0.0, 1.0], dtype=x.dtype)
        v = jnp.stack([jnp.sin(tv), jnp.zeros_like(tv), jnp.cos(tv)])
        l = jnp.stack([jnp.sin(tl) * jnp.cos(phi), jnp.sin(tl) * jnp.sin(phi), jnp.cos(tl)])
        base = x[3] * jnp.asarray(_TINT, dtype=x.dtype)
        return _weighted(brdf.evaluate(n, v, l, base, x[4], x[5]))

    th = (0.2, 0.7, 1.2)
    grid = product_grid(th, th, (0.5, 1.5, 2.8), (0.3, 0.9), (0.0, 0.6), (0.2, 0.6))
    return Spec("evaluate", fn, ("θv", "θl", "φ", "base_color", "metallic", "roughness"), grid,
                 ((), (), (0.0, math.pi), (), (), _ROUGH_KINKS))


# --- color -------------------------------------------------------------------------------------
_CHANNEL_RATIOS = (1.0, 0.55, 0.2)


def _rgb_grid(scales) -> np.ndarray:
    """Colors s · (1, 0.55, 0.2) and the same channels permuted: distinct channels, so min/max are smooth."""
    rows = []
    for s in scales:
        for perm in ((0, 1, 2), (2, 0, 1)):
            rows.append([s * _CHANNEL_RATIOS[i] for i in perm])
    return np.array(rows, dtype=np.float64)


def _khronos_skip(p):
    # Branches switch at min(x) = 0.08 and at max(x - offset) = 0.76.
    low = p.min(axis=1)
    offset = np.where(low < 0.08, low - 6.25 * low * low, 0.04)
    peak = p.max(axis=1) - offset
    return (np.abs(low - 0.08) < KINK_MARGIN * 5) | (np.abs(peak - 0.76) < KINK_MARGIN * 5)


def _aces_hill_skip(p):
    # The output is clipped to [0, 1]; skip points whose unclipped output is near either bound.
    m_in, m_out = np.asarray(color._ACES_INPUT, np.float64), np.asarray(color._ACES_OUTPUT, np.float64)
    c = p @ m_in.T
    c = (c * (c + 0.0245786) - 0.000090537) / (c * (0.983729 * c + 0.4329510) + 0.238081)
    out = c @ m_out.T
    return np.any((np.abs(out) < 0.01) | (np.abs(out - 1.0) < 0.01), axis=1)


def _color_specs() -> list:
    # sRGB curves: kinks at the IEC breakpoints (the piecewise definitions meet with a slope jump
    # of ~1e-4 relative, and the linear-branch floor); values straddle both branches.
    lin = (0.001, 0.002, 0.01, 0.05, 0.2, 0.5, 0.9)
    enc = (0.01, 0.03, 0.06, 0.2, 0.5, 0.9)
    scales = (0.05, 0.3, 0.6, 1.5, 4.0)
    specs = [
        Spec("srgb_to_linear", lambda x: color.srgb_to_linear(x[0]), ("x",), product_grid(enc), ((0.04045,),)),
        Spec("linear_to_srgb", lambda x: color.linear_to_srgb(x[0]), ("x",), product_grid(lin), ((0.0031308,),)),
        Spec("apply_exposure", lambda x: color.apply_exposure(x[0], x[1]), ("x", "ev"),
              product_grid((0.1, 0.5, 2.0), (-2.0, 0.0, 1.5)), ((), ())),
        Spec("tonemap_reinhard", lambda x: _weighted(color.tonemap_reinhard(x)), ("r", "g", "b"),
              _rgb_grid(scales), ((0.0,),) * 3),
        # Narkowicz's curve reaches 1 (and is clipped) at x ≈ 7.24.
        Spec("tonemap_aces_narkowicz", lambda x: _weighted(color.tonemap_aces_narkowicz(x)), ("r", "g", "b"),
              _rgb_grid(scales + (9.0,)), ((0.0, 7.2376),) * 3),
        Spec("tonemap_aces_hill", lambda x: _weighted(color.tonemap_aces_hill(x)), ("r", "g", "b"),
              _rgb_grid(scales), ((0.0,),) * 3, skip=_aces_hill_skip),
        Spec("tonemap_khronos_neutral", lambda x: _weighted(color.tonemap_khronos_neutral(x)), ("r", "g", "b"),
              _rgb_grid((0.02, 0.05, 0.3, 0.6, 1.0, 2.0, 4.0)), ((0.0,),) * 3, skip=_khronos_skip),
    ]
    return specs


def all_specs() -> list:
    """Every function `pbrfit.checks.gradcheck.run_checks` checks (one `Spec` each)."""
    return (
        _scalar_terms()
        + [_evaluate_cosines_spec(m) for m in MODEL_VARIANTS]
        + [_evaluate_spec()]
        + _color_specs()
    )
