"""Gradient checks: autodiff against central finite differences, in float64 (``pbrfit check-grads``).

Every public BRDF term, `brdf.evaluate_cosines` under each `Model` variant, `brdf.evaluate`, and the
sRGB curves, exposure and tone maps of `color` are checked at 1st order (gradient) and 2nd order
(Hessian) over a grid of cosines, alpha / roughness and colors.

Autodiff (forward over reverse) is compared with float64 central finite differences,
Richardson-extrapolated (`pbrfit.finite_differences`: the stencils, steps and error measure). Points
within `KINK_MARGIN` of a clamp or branch switch are skipped (counted in `CheckResult.skipped`); a
check passes when its worst point's relative error is within `TOLERANCE[order]`.

Finite differences cannot reach the ends of the domains (a cosine at 0 or 1, roughness at its
floor), where the project promises finite values and gradients: `run_ends` evaluates every term
there, at each input's kinks and about a float32 ulp either side, in float32 and in float64.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
import zlib
from typing import Callable, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import brdf, color
from .finite_differences import KINK_MARGIN, STEP_1, STEP_2, fd_estimates, rel_error, stencil_points
from .model import Model

__all__ = ["CheckResult", "run_checks", "print_report", "all_specs", "model_label", "MODEL_VARIANTS", "TOLERANCE"]

#: Pass thresholds on the maximum relative error, by order (0: the share of points at the
#: domains' ends where a value or gradient is not finite).
TOLERANCE = {0: 0.0, 1: 1e-5, 2: 1e-4}

#: Fixed weights that turn an RGB (or other vector) output into the scalar that is differentiated;
#: unequal so that a wrong channel cannot cancel.
_RGB_WEIGHTS = (0.6, 0.3, 0.1)
#: A grey base color is a scalar input times this tint (three distinct channels).
_TINT = (1.0, 0.7, 0.4)


@dataclasses.dataclass(frozen=True)
class CheckResult:
    """Outcome of one gradient check.

    term: what was differentiated (a function name, with the Model variant for evaluate_cosines).
    order: 1 (gradient) or 2 (Hessian) against finite differences, or 0: the values and gradients
    at the ends of the inputs' domains are finite (`run_ends`; max_rel_error is then the share of
    points where one is not, and the tolerance 0). dtype: what it ran in.
    max_rel_error: worst relative error over the grid.
    worst_point: the inputs at the worst point, the derivative component (``wrt``), and the
    autodiff and finite-difference values there. passed: max_rel_error <= tolerance.
    checked / skipped: grid points compared / skipped for lying within `KINK_MARGIN` of a kink.
    """

    term: str
    order: int
    max_rel_error: float
    worst_point: dict
    passed: bool
    tolerance: float
    checked: int = 0
    skipped: int = 0
    dtype: str = "float64"


@dataclasses.dataclass(frozen=True)
class _Spec:
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


def _grid(*axes) -> np.ndarray:
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
        _Spec("alpha_from_roughness", lambda x: brdf.alpha_from_roughness(x[0]), ("roughness",), _grid(r), (rk,)),
        _Spec("d_ggx", lambda x: brdf.d_ggx(x[0], x[1]), ("n·h", "alpha"), _grid(c, a), (ck, ak)),
        _Spec("d_beckmann", lambda x: brdf.d_beckmann(x[0], x[1]), ("n·h", "alpha"), _grid(c, a), (ck, ak)),
        _Spec("lambda_ggx", lambda x: brdf.lambda_ggx(x[0], x[1]), ("n·x", "alpha"), _grid(c, a), (ck, ak)),
        _Spec("g1_smith_ggx", lambda x: brdf.g1_smith_ggx(x[0], x[1]), ("n·x", "alpha"), _grid(c, a), (ck, ak)),
        _Spec("lambda_beckmann", lambda x: brdf.lambda_beckmann(x[0], x[1]), ("n·x", "alpha"), _grid(c, a), (ck, ak),
              skip=_beckmann_cap_skip),
        _Spec("g1_smith_beckmann", lambda x: brdf.g1_smith_beckmann(x[0], x[1]), ("n·x", "alpha"), _grid(c, a),
              (ck, ak), skip=_beckmann_cap_skip),
        _Spec("v_smith_beckmann_correlated", lambda x: brdf.v_smith_beckmann_correlated(x[0], x[1], x[2]),
              ("n·v", "n·l", "alpha"), _grid(c, c, a), (ck, ck, ak),
              skip=lambda p: _beckmann_cap_skip(p[:, [0, 2]]) | _beckmann_cap_skip(p[:, [1, 2]])),
    ]
    for name in ("g2_smith_ggx_correlated", "g2_smith_ggx_separable", "v_smith_ggx_correlated", "v_smith_ggx_separable"):
        fn = getattr(brdf, name)
        specs.append(_Spec(name, lambda x, fn=fn: fn(x[0], x[1], x[2]), ("n·v", "n·l", "alpha"), _grid(c, c, a), (ck, ck, ak)))
    k_grid = (0.01, 0.1, 0.3, 0.6)
    k_kinks = (brdf.K_MIN,)
    specs += [
        _Spec("k_direct", lambda x: brdf.k_direct(x[0]), ("roughness",), _grid(r), ((),)),
        _Spec("k_ibl", lambda x: brdf.k_ibl(x[0]), ("alpha",), _grid(a), ((),)),
        _Spec("g_schlick_ggx", lambda x: brdf.g_schlick_ggx(x[0], x[1]), ("n·x", "k"), _grid(c, k_grid), (ck, k_kinks)),
        _Spec("g2_schlick_ggx", lambda x: brdf.g2_schlick_ggx(x[0], x[1], x[2]), ("n·v", "n·l", "k"),
              _grid(c, c, k_grid), (ck, ck, k_kinks)),
        _Spec("v_schlick_ggx", lambda x: brdf.v_schlick_ggx(x[0], x[1], x[2]), ("n·v", "n·l", "k"),
              _grid(c, c, k_grid), (ck, ck, k_kinks)),
        _Spec("f_schlick", lambda x: brdf.f_schlick(x[0], x[1], x[2]), ("v·h", "f0", "f90"),
              _grid(c, (0.04, 0.5, 0.9), (0.5, 1.0)), (ck, (), ())),
        _Spec("f_dielectric", lambda x: brdf.f_dielectric(x[0], x[1]), ("cos_theta", "ior"),
              _grid(c, (1.2, 1.5, 2.4)), (ck, ())),
        _Spec("f0_from_ior", lambda x: brdf.f0_from_ior(x[0]), ("ior",), _grid((1.1, 1.5, 2.0, 3.0)), ((),)),
        _Spec("diffuse_lambert", lambda x: brdf.diffuse_lambert(x[0], x[1], x[2], x[3]), ("n·v", "n·l", "l·h", "roughness"),
              _grid(cos3, cos3, cos3, r), (ck, ck, ck, ())),
        _Spec("diffuse_burley", lambda x: brdf.diffuse_burley(x[0], x[1], x[2], x[3]), ("n·v", "n·l", "l·h", "roughness"),
              _grid(cos3, cos3, cos3, r), (ck, ck, ck, ())),
        _Spec("half_vector_cosines", lambda x: _weighted(jnp.stack(brdf.half_vector_cosines(x[0], x[1], x[2]))),
              ("n·v", "n·l", "v·l"), _grid((0.3, 0.6, 0.9), (0.3, 0.6, 0.9), (-0.5, 0.0, 0.5, 0.9)), ((), (), (-1.0,)),
              skip=_half_vector_skip),
        _Spec("v_plus_l_sq", lambda x: brdf.v_plus_l_sq(x[:3], x[3:]), ("v_x", "v_y", "v_z", "l_x", "l_y", "l_z"),
              _grid((-0.6, 0.3), (0.2, 0.8), (0.1, 0.7), (-0.5, 0.4), (-0.3, 0.6), (0.2, 0.9)), ((),) * 6),
        _Spec("half_vector_sin2", lambda x: brdf.half_vector_sin2(x[:3] / jnp.linalg.norm(x[:3]), x[3:6], x[6:]),
              ("n_x", "n_y", "n_z", "v_x", "v_y", "v_z", "l_x", "l_y", "l_z"),
              _grid((0.1, 0.4), (0.2,), (0.9,), (-0.6, 0.3), (0.2,), (0.7,), (0.5,), (-0.3, 0.6), (0.6,)), ((),) * 9),
        _Spec("safe_normalize", lambda x: _weighted(brdf.safe_normalize(x)), ("x", "y", "z"),
              _grid((-0.7, 0.2, 1.5), (-0.3, 0.4), (0.1, 0.9)), ((), (), ())),
        _Spec("specular_dv", lambda x: brdf.specular_dv(Model(), x[0], x[1], x[2], x[3]), ("n·v", "n·l", "n·h", "roughness"),
              _grid(cos3, cos3, cos3, r), (ck, ck, ck, rk)),
        _Spec("specular_f0", lambda x: _weighted(brdf.specular_f0(x[0] * jnp.asarray(_TINT), x[1])),
              ("base_color", "metallic"), _grid((0.2, 0.8), (0.0, 0.4, 1.0)), ((), ())),
        _Spec("diffuse_color", lambda x: _weighted(brdf.diffuse_color(x[0] * jnp.asarray(_TINT), x[1])),
              ("base_color", "metallic"), _grid((0.2, 0.8), (0.0, 0.4, 1.0)), ((), ())),
        _Spec("energy_compensation",
              lambda x: _weighted(brdf.energy_compensation(x[0] * jnp.asarray(_TINT), jnp.stack([x[1], x[2]]))),
              ("f0", "dfg_scale", "dfg_bias"), _grid((0.04, 0.5, 1.0), (0.3, 0.7, 0.95), (0.0, 0.02, 0.05)), ((), (), ())),
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


def _evaluate_cosines_spec(model: Model) -> _Spec:
    def fn(x):
        base = x[4] * jnp.asarray(_TINT, dtype=x.dtype)
        dfg = jnp.asarray(_DFG, dtype=x.dtype) if model.multiscatter else None
        out = brdf.evaluate_cosines(x[0], x[1], x[2], x[3], base, x[5][None], x[6][None], model, dfg)
        return _weighted(out)

    # 216 points: the composition is what is checked here (each term has its own denser grid).
    grid = _grid((0.2, 0.7), (0.2, 0.7), (0.5, 0.9, 0.98), (0.3, 0.9), (0.7,), (0.0, 0.5, 1.0), (0.1, 0.4, 0.9))
    kinks = (_COS_KINKS, _COS_KINKS, _COS_KINKS, _COS_KINKS, (), (), _ROUGH_KINKS)
    return _Spec(f"evaluate_cosines[{model_label(model)}]", fn,
                 ("n·v", "n·l", "n·h", "v·h", "base_color", "metallic", "roughness"), grid, kinks)


def _evaluate_spec() -> _Spec:
    """`evaluate` from directions: v and l at polar angles θv, θl, azimuth φ between them, n = +z."""

    def fn(x):
        tv, tl, phi = x[0], x[1], x[2]
        n = jnp.array([0.0, 0.0, 1.0], dtype=x.dtype)
        v = jnp.stack([jnp.sin(tv), jnp.zeros_like(tv), jnp.cos(tv)])
        l = jnp.stack([jnp.sin(tl) * jnp.cos(phi), jnp.sin(tl) * jnp.sin(phi), jnp.cos(tl)])
        base = x[3] * jnp.asarray(_TINT, dtype=x.dtype)
        return _weighted(brdf.evaluate(n, v, l, base, x[4], x[5]))

    th = (0.2, 0.7, 1.2)
    grid = _grid(th, th, (0.5, 1.5, 2.8), (0.3, 0.9), (0.0, 0.6), (0.2, 0.6))
    return _Spec("evaluate", fn, ("θv", "θl", "φ", "base_color", "metallic", "roughness"), grid,
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
        _Spec("srgb_to_linear", lambda x: color.srgb_to_linear(x[0]), ("x",), _grid(enc), ((0.04045,),)),
        _Spec("linear_to_srgb", lambda x: color.linear_to_srgb(x[0]), ("x",), _grid(lin), ((0.0031308,),)),
        _Spec("apply_exposure", lambda x: color.apply_exposure(x[0], x[1]), ("x", "ev"),
              _grid((0.1, 0.5, 2.0), (-2.0, 0.0, 1.5)), ((), ())),
        _Spec("tonemap_reinhard", lambda x: _weighted(color.tonemap_reinhard(x)), ("r", "g", "b"),
              _rgb_grid(scales), ((0.0,),) * 3),
        # Narkowicz's curve reaches 1 (and is clipped) at x ≈ 7.24.
        _Spec("tonemap_aces_narkowicz", lambda x: _weighted(color.tonemap_aces_narkowicz(x)), ("r", "g", "b"),
              _rgb_grid(scales + (9.0,)), ((0.0, 7.2376),) * 3),
        _Spec("tonemap_aces_hill", lambda x: _weighted(color.tonemap_aces_hill(x)), ("r", "g", "b"),
              _rgb_grid(scales), ((0.0,),) * 3, skip=_aces_hill_skip),
        _Spec("tonemap_khronos_neutral", lambda x: _weighted(color.tonemap_khronos_neutral(x)), ("r", "g", "b"),
              _rgb_grid((0.02, 0.05, 0.3, 0.6, 1.0, 2.0, 4.0)), ((0.0,),) * 3, skip=_khronos_skip),
    ]
    return specs


def all_specs() -> list:
    """Every check `run_checks` performs (one `_Spec` per differentiated function)."""
    return (
        _scalar_terms()
        + [_evaluate_cosines_spec(m) for m in MODEL_VARIANTS]
        + [_evaluate_spec()]
        + _color_specs()
    )


def _prepare(spec: _Spec, h1: float, h2: float):
    """The grid minus points near kinks, the stencil points, and the autodiff+stencil function."""
    grid = np.asarray(spec.grid, dtype=np.float64)
    keep = np.ones(len(grid), dtype=bool)
    for i, kinks in enumerate(spec.kinks):
        for kink in kinks:
            keep &= np.abs(grid[:, i] - kink) >= KINK_MARGIN
    if spec.skip is not None:
        keep &= ~spec.skip(grid)
    x = grid[keep]
    pts, pairs = stencil_points(x, h1, h2)
    fn = spec.fn

    def one(xi):
        def grad_aux(xi):
            g = jax.grad(fn)(xi)
            return g, g

        return jax.jacfwd(grad_aux, has_aux=True)(xi)  # (Hessian, gradient), forward over reverse

    def run(xs, ps):
        hess, grad = jax.vmap(one)(xs)
        return jax.vmap(fn)(ps), grad, hess

    return run, (jnp.asarray(x), jnp.asarray(pts)), x, pairs, int((~keep).sum())


def _compare(spec: _Spec, x, pairs, skipped, outputs, h1: float, h2: float) -> list:
    values, g_ad, h_ad = (np.asarray(a, dtype=np.float64) for a in outputs)
    fval, g_fd, h_fd = fd_estimates(values, len(x), x.shape[1], pairs, h1, h2)
    results = []
    for order, ad, fd in ((1, g_ad, g_fd), (2, h_ad, h_fd)):
        err = rel_error(ad, fd, fval, order)
        idx = np.unravel_index(int(np.argmax(err)), err.shape)
        worst = float(err[idx])
        point = {name: float(x[idx[0], i]) for i, name in enumerate(spec.names)}
        comp = [spec.names[j] for j in idx[1:]]
        point["wrt"] = "d/d" + comp[0] if order == 1 else f"d²/d{comp[0]} d{comp[1]}"
        point["autodiff"] = float(ad[idx])
        point["finite_difference"] = float(fd[idx])
        tol = TOLERANCE[order]
        results.append(CheckResult(spec.term, order, worst, point, bool(worst <= tol), tol, len(x), skipped))
    return results


#: The checked functions are small and run once, so compilation dominates the run time: they
#: are compiled as one XLA program (one fixed overhead), with XLA's cheaper backend passes.
_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


# --- The ends of the domains ------------------------------------------------------------------
#: Where the sweep evaluates around each kink (a clamp, a branch switch, a domain's end): on it,
#: and about one float32 ulp of 1 either side.
ENDS_OFFSETS = (0.0, -1e-7, 1e-7)
#: The sweep runs in float32, as a fit does, and in float64.
ENDS_DTYPES = (np.float32, np.float64)
#: Most points per term: a larger product of the inputs' ends is sampled (a fixed draw), which
#: keeps `evaluate_cosines`' 118,098 combinations per model from taking most of the run time.
ENDS_MAX_POINTS = 8192


def ends_grid(spec: _Spec) -> np.ndarray:
    """Points at the ends of ``spec``'s domains: per input, its kinks ± `ENDS_OFFSETS` (or, for an
    input without kinks, the least and greatest values of its grid), every combination. Where
    there are more than `ENDS_MAX_POINTS`, every point with each input exactly on an end is
    kept, and the rest drawn from the others (a draw of its own per term)."""
    grid = np.asarray(spec.grid)
    ends = [sorted(kinks) or sorted({float(grid[:, i].min()), float(grid[:, i].max())})
            for i, kinks in enumerate(spec.kinks)]
    axes = [sorted({k + d for k in kinks for d in ENDS_OFFSETS}) if kinks else ends[i]
            for i, kinks in enumerate(spec.kinks)]
    points = _grid(*axes)
    if len(points) <= ENDS_MAX_POINTS:
        return points
    on_ends = np.all([np.isin(points[:, i], ends[i]) for i in range(points.shape[1])], axis=0)
    near = np.flatnonzero(~on_ends)
    rng = np.random.default_rng(zlib.crc32(spec.term.encode()))
    drawn = rng.choice(near, max(ENDS_MAX_POINTS - int(on_ends.sum()), 0), replace=False)
    return points[np.sort(np.concatenate([np.flatnonzero(on_ends), drawn]))]


def _ends_results(spec: _Spec, grid: np.ndarray, outputs, dtype) -> CheckResult:
    values, grads = (np.asarray(a, np.float64) for a in outputs)
    bad = ~(np.isfinite(values) & np.all(np.isfinite(grads), axis=1))
    point = {}
    if bad.any():
        i = int(np.argmax(bad))
        point = {name: float(grid[i, j]) for j, name in enumerate(spec.names)}
        point.update(value=float(values[i]), gradient=[float(g) for g in grads[i]])
    return CheckResult(spec.term, 0, float(bad.mean()), point, not bad.any(), TOLERANCE[0], len(grid), 0,
                       np.dtype(dtype).name)


def run_ends(specs: Optional[Sequence[_Spec]] = None) -> list:
    """Values and gradients at the ends of every input's domain (`ends_grid`), in float32 and in
    float64: one `CheckResult` (order 0) per (term, dtype), passed where all are finite. Finite
    differences cannot reach there (a stencil straddles the kink); the derivatives' values at
    the ends are tested in ``tests/test_brdf.py`` (the one-sided derivative from inside)."""
    specs = all_specs() if specs is None else list(specs)
    grids = [ends_grid(spec) for spec in specs]
    results = []
    for dtype in ENDS_DTYPES:
        with jax.enable_x64(dtype == np.float64):
            runs = [jax.vmap(jax.value_and_grad(spec.fn)) for spec in specs]
            args = [jnp.asarray(g.astype(dtype)) for g in grids]
            lowered = jax.jit(lambda args: [run(a) for run, a in zip(runs, args)]).lower(args)
            try:
                program = lowered.compile(_COMPILER_OPTIONS)
            except Exception:  # an XLA build without these options: compile with the defaults
                program = lowered.compile()
            outputs = program(args)
        results.extend(_ends_results(spec, grid, out, dtype) for spec, grid, out in zip(specs, grids, outputs))
    return results


def run_checks(specs: Optional[Sequence[_Spec]] = None, ends: bool = True) -> list:
    """Run every gradient check; returns one `CheckResult` per (term, order), and with ``ends``
    the sweep of the domains' ends (`run_ends`, order 0, one per term and dtype) after them.

    For each function: autodiff gradient and Hessian (forward over reverse) at every grid point,
    against the Richardson-extrapolated central differences of its values, in float64 (see
    module docstring). ``specs`` defaults to `all_specs()`.
    """
    h1, h2 = STEP_1, STEP_2
    with jax.enable_x64(True):
        specs = all_specs() if specs is None else list(specs)
        prepared = [_prepare(spec, h1, h2) for spec in specs]
        runs = [p[0] for p in prepared]
        args = [p[1] for p in prepared]
        lowered = jax.jit(lambda args: [run(*a) for run, a in zip(runs, args)]).lower(args)
        try:
            program = lowered.compile(_COMPILER_OPTIONS)
        except Exception:  # an XLA build without these options: compile with the defaults
            program = lowered.compile()
        outputs = program(args)
        results = []
        for spec, prep, out in zip(specs, prepared, outputs):
            _, _, x, pairs, skipped = prep
            results.extend(_compare(spec, x, pairs, skipped, out, h1, h2))
    return results + (run_ends(specs) if ends else [])


# --- Report ------------------------------------------------------------------------------------
def _fmt_point(point: dict) -> str:
    inputs = [f"{k}={v:.4g}" for k, v in point.items()
              if k not in ("wrt", "autodiff", "finite_difference", "value", "gradient")]
    extra = f" {point['wrt']}" if "wrt" in point else ""
    return " ".join(inputs) + extra


def print_report(results: Sequence[CheckResult], quiet: bool = False) -> bool:
    """Print the results table, the named numerical floors and a summary line; return overall pass."""
    from . import lights  # floors reported alongside the BRDF's

    ok = all(r.passed for r in results)
    rows = [r for r in results if not (quiet and r.passed)]
    if rows:
        width = max(len(r.term) for r in rows)
        print(f"{'term':<{width}}  {'check':<12}  max rel error  tol      points  skipped  result  worst point")
        for r in rows:
            check = f"ends {r.dtype}" if r.order == 0 else f"order {r.order}"
            print(
                f"{r.term:<{width}}  {check:<12}  {r.max_rel_error:13.2e}  {r.tolerance:7.0e}  {r.checked:>6}  "
                f"{r.skipped:>7}  {'pass' if r.passed else 'FAIL':<6}  {_fmt_point(r.worst_point)}"
            )
    if not quiet:
        print()
        print("numerical floors (brdf.FLOORS, lights.MIN_DISTANCE):")
        floors = dict(brdf.FLOORS)
        floors["MIN_DISTANCE (lights)"] = lights.MIN_DISTANCE
        for name, value in floors.items():
            print(f"  {name:<22} {value:.6g}")
        print(
            f"finite differences: float64, central, Richardson-extrapolated, steps {STEP_1:g} (1st order) and "
            f"{STEP_2:g} (2nd order); points within {KINK_MARGIN:g} of a clamp or branch switch are skipped"
        )
        print("ends: values and gradients finite at each input's kinks (clamps, branch switches, domain ends) "
              f"and {ENDS_OFFSETS[-1]:g} either side, in float32 and float64; max rel error is the share that is not")
    failed = [r for r in results if not r.passed]
    worst1 = max((r.max_rel_error for r in results if r.order == 1), default=0.0)
    worst2 = max((r.max_rel_error for r in results if r.order == 2), default=0.0)
    terms = len({r.term for r in results})
    ends = [r for r in results if r.order == 0]
    swept = f"; {sum(r.checked for r in ends)} points at the domains' ends" if ends else ""
    print(
        f"check-grads: {'PASS' if ok else 'FAIL'}: {terms} terms, {len(results)} checks, {len(failed)} failed; "
        f"max rel error {worst1:.1e} (1st order), {worst2:.1e} (2nd order){swept}"
    )
    return ok


def main() -> int:  # pragma: no cover - convenience for `python -m pbrfit.gradcheck`
    t0 = time.perf_counter()
    ok = print_report(run_checks())
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0 if ok else 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
