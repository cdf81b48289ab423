"""Gradient checks: autodiff against central finite differences, in float64 (``pbrfit check-grads``).

Every public BRDF term, `brdf.evaluate_cosines` under each `Model` variant, `brdf.evaluate`, and the
sRGB curves, exposure and tone maps of `color` (`pbrfit.checks.terms`: each function, its grid
and its kinks) are checked at 1st order (gradient) and 2nd order (Hessian) over a grid of cosines,
alpha / roughness and colors.

Autodiff (forward over reverse) is compared with float64 central finite differences,
Richardson-extrapolated (`pbrfit.checks.finite_differences`: the stencils, steps and error measure). Points
within `KINK_MARGIN` of a clamp or branch switch are skipped (counted in `CheckResult.skipped`); a
check passes when its worst point's relative error is within `TOLERANCE[order]`.

Finite differences cannot reach the ends of the domains (a cosine at 0 or 1, roughness at its
floor), where the project promises finite values and gradients: `run_ends` evaluates every term
there, at each input's kinks and about a float32 ulp either side, in float32 and in float64.
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..physics import brdf, lights
from .finite_differences import KINK_MARGIN, STEP_1, STEP_2, fd_estimates, rel_error, stencil_points
from .terms import Spec, all_specs, product_grid
from ..xla import FAST_COMPILE, compile_lowered

__all__ = ["CheckResult", "run_checks", "run_ends", "ends_grid", "print_report", "TOLERANCE", "ENDS_OFFSETS",
           "ENDS_DTYPES", "ENDS_MAX_POINTS"]

#: Pass thresholds on the maximum relative error, by order (0: the share of points at the
#: domains' ends where a value or gradient is not finite).
TOLERANCE = {0: 0.0, 1: 1e-5, 2: 1e-4}


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


def _prepare(spec: Spec, h1: float, h2: float):
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


def _compare(spec: Spec, x, pairs, skipped, outputs, h1: float, h2: float) -> list:
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
#: are compiled as one XLA program (one fixed overhead), with XLA's cheaper backend passes and
#: `pbrfit.xla.FAST_COMPILE` (the whole check's compile 14 s without it, 9 s with it).
_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True, **FAST_COMPILE}


def _run_as_one(runs: Sequence, args: Sequence) -> list:
    """[run(a) for run, a in zip(runs, args)], compiled as one XLA program with `_COMPILER_OPTIONS`."""
    lowered = jax.jit(lambda args: [run(a) for run, a in zip(runs, args)]).lower(list(args))
    program = compile_lowered(lowered, _COMPILER_OPTIONS)
    return program(list(args))


# --- The ends of the domains ------------------------------------------------------------------
#: Where the sweep evaluates around each kink (a clamp, a branch switch, a domain's end): on it,
#: and about one float32 ulp of 1 either side.
ENDS_OFFSETS = (0.0, -1e-7, 1e-7)
#: The sweep runs in float32, as a fit does, and in float64.
ENDS_DTYPES = (np.float32, np.float64)
#: Most points per term: a larger product of the inputs' ends is sampled (a fixed draw), which
#: keeps `evaluate_cosines`' 118,098 combinations per model from taking most of the run time.
ENDS_MAX_POINTS = 8192


def ends_grid(spec: Spec) -> np.ndarray:
    """Points at the ends of ``spec``'s domains: per input, its kinks ± `ENDS_OFFSETS` (or, for an
    input without kinks, the least and greatest values of its grid), every combination. Where
    there are more than `ENDS_MAX_POINTS`, every point with each input exactly on an end is
    kept, and the rest drawn from the others (a draw of its own per term)."""
    grid = np.asarray(spec.grid)
    ends = [sorted(kinks) or sorted({float(grid[:, i].min()), float(grid[:, i].max())})
            for i, kinks in enumerate(spec.kinks)]
    axes = [sorted({k + d for k in kinks for d in ENDS_OFFSETS}) if kinks else ends[i]
            for i, kinks in enumerate(spec.kinks)]
    points = product_grid(*axes)
    if len(points) <= ENDS_MAX_POINTS:
        return points
    on_ends = np.all([np.isin(points[:, i], ends[i]) for i in range(points.shape[1])], axis=0)
    near = np.flatnonzero(~on_ends)
    rng = np.random.default_rng(zlib.crc32(spec.term.encode()))
    drawn = rng.choice(near, max(ENDS_MAX_POINTS - int(on_ends.sum()), 0), replace=False)
    return points[np.sort(np.concatenate([np.flatnonzero(on_ends), drawn]))]


def _ends_results(spec: Spec, grid: np.ndarray, outputs, dtype) -> CheckResult:
    values, grads = (np.asarray(a, np.float64) for a in outputs)
    bad = ~(np.isfinite(values) & np.all(np.isfinite(grads), axis=1))
    point = {}
    if bad.any():
        i = int(np.argmax(bad))
        point = {name: float(grid[i, j]) for j, name in enumerate(spec.names)}
        point.update(value=float(values[i]), gradient=[float(g) for g in grads[i]])
    return CheckResult(spec.term, 0, float(bad.mean()), point, not bad.any(), TOLERANCE[0], len(grid), 0,
                       np.dtype(dtype).name)


def run_ends(specs: Optional[Sequence[Spec]] = None) -> list:
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
            outputs = _run_as_one(runs, args)
        results.extend(_ends_results(spec, grid, out, dtype) for spec, grid, out in zip(specs, grids, outputs))
    return results


def run_checks(specs: Optional[Sequence[Spec]] = None, ends: bool = True) -> list:
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
        outputs = _run_as_one([lambda a, run=p[0]: run(*a) for p in prepared], [p[1] for p in prepared])
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


def main() -> int:  # pragma: no cover - convenience for `python -m pbrfit.checks.gradcheck`
    t0 = time.perf_counter()
    ok = print_report(run_checks())
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0 if ok else 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
