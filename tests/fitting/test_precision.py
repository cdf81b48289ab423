"""Every float32 contraction pbrfit compiles runs at full precision.

JAX's default precision lets a GPU multiply float32 matrices in TF32 (a 10-bit mantissa). On an
H100 that moved the ACES tone map by 2e-3 and made it non-monotone, and broke the 1e-5 agreement
of the environment resampling, the irradiance map and chunked rendering. The CPU has no TF32, so
these tests read the lowered programs instead: every ``dot_general`` must ask for HIGHEST.
Lowering traces without compiling, so they are cheap.
"""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit.physics.color import TONEMAPS, encode
from pbrfit.lighting.environment import Environment, procedural_sky, resample_equirect
from pbrfit.lighting.ibl import IBLSettings, build_ibl, irradiance_map, sh9_coefficients
from pbrfit.fitting.initialisation import coordinate_search, grid_initialise, parity_classes
from pbrfit.physics.lights import point_light
from pbrfit.physics.material import Material
from pbrfit.physics.model import Model
from pbrfit.lighting.montecarlo import monte_carlo_radiance
from pbrfit.fitting.observations import neighbour_pairs, observations_from_views, texel_layout
from pbrfit.fitting.solvers.optx import OPTX_SOLVERS, make_solver, optx_solve
from pbrfit.lighting.lobe_integrals import integrate_lobes
from pbrfit.lighting.pixel_ibl import PixelIBL, lobes_for
from pbrfit.render.shade import ViewInputs, light_arrays, radiance_view
from pbrfit.fitting.normal_matrix import neighbour_blocks, normal_blocks
from pbrfit.fitting.objective import Problem, linearize
from pbrfit.fitting.stages.selection import profile_hessian, uniform_direction
from pbrfit.fitting.solvers.structured import StructuredLM, solve

_DOT = re.compile(r"dot_general.*?precision = \[(\w+), (\w+)\]")


def _low_precision_dots(lowered) -> list[str]:
    """The dot_general lines of a lowered program that do not ask for HIGHEST."""
    text = lowered.as_text()
    lines = [line.strip() for line in text.splitlines() if "dot_general" in line]
    bad = [line for line in lines if not (m := _DOT.search(line)) or m.groups() != ("HIGHEST", "HIGHEST")]
    return bad


def _check(fn, *args, **kwargs):
    lowered = (fn if hasattr(fn, "lower") else jax.jit(fn)).lower(*args, **kwargs)
    bad = _low_precision_dots(lowered)
    assert not bad, f"{len(bad)} contraction(s) at default precision, first: {bad[0][:200]}"


def test_the_check_sees_default_precision():
    a = jnp.ones((3, 3))
    assert _low_precision_dots(jax.jit(lambda x: x @ x).lower(a))
    assert not _low_precision_dots(jax.jit(lambda x: jnp.matmul(x, x, precision="highest")).lower(a))


@pytest.mark.parametrize("tonemap", TONEMAPS)
def test_tone_maps(tonemap):
    _check(lambda x: encode(x, 0.5, tonemap, "srgb"), jnp.ones((4, 3)))


def test_environment_tables():
    sky = procedural_sky(16).radiance
    _check(lambda r: resample_equirect(r, 8, 16), sky)
    _check(lambda r: resample_equirect(r, 6, 12), sky)
    _check(sh9_coefficients, sky)
    _check(lambda r: irradiance_map(r, 4), sky)
    settings = IBLSettings(lut_size=8, lut_samples=16, prefilter_levels=3, prefilter_resolution=8,
                           prefilter_samples=8, irradiance_resolution=4)
    _check(lambda r: build_ibl(Environment(r), settings), sky)


def _view(n=6):
    p = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n)), -1).reshape(-1, 2)
    points = np.concatenate([p, np.zeros((len(p), 1))], -1)
    ll, lr = light_arrays([point_light((0.3, 0.2, 2.0), (1, 1, 1), 5.0)], points)
    m = len(points)
    view = np.tile([[0.0, 0.6, 0.8]], (m, 1)).astype(np.float32)
    return ViewInputs(pixel=jnp.arange(m, dtype=jnp.int32), uv=jnp.asarray(p + 0.5, jnp.float32),
                      normal=jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (m, 1)),
                      tangent=jnp.tile(jnp.array([[1.0, 0.0, 0.0, 1.0]]), (m, 1)),
                      view=jnp.asarray(view), light_l=ll, light_radiance=lr, shape=(n, n))


def test_rendering():
    view = _view()
    material = Material.uniform((0.5, 0.4, 0.3), 0.2, 0.4)
    settings = IBLSettings(lut_size=8, lut_samples=16, prefilter_levels=3, prefilter_resolution=8,
                           prefilter_samples=8, irradiance_resolution=4)
    tables = build_ibl(procedural_sky(16), settings)
    for model in (Model(), Model(ibl="split_sum", multiscatter=True, diffuse="burley")):
        _check(lambda v: radiance_view(v, material, model, tables if model.ibl else None), view)
    env = procedural_sky(16)
    per_pixel = Model(ibl="per_pixel", multiscatter=True)
    _check(lambda t: radiance_view(view, material, per_pixel, t), _zero_table(view.pixel.shape[0], per_pixel))
    n = jnp.tile(jnp.array([[0.0, 1.0, 0.0]]), (4, 1))
    _check(lambda nn: monte_carlo_radiance(env, nn, nn, jnp.full((4, 3), 0.5), jnp.zeros((4, 1)),
                                           jnp.full((4, 1), 0.5), samples=4, key=jax.random.PRNGKey(0)), n)


def _zero_table(points: int, model: Model, levels: int = 3) -> PixelIBL:
    """Per-pixel integrals of the right shape: lowering reads shapes only, so none are computed."""
    lobes = lobes_for(model)
    return PixelIBL(jnp.zeros((points, levels, len(lobes), 3)), lobes)


def _problem():
    view = _view()
    img = np.zeros((6, 6, 3), np.float32) + 0.2
    obs = observations_from_views([view], [img])
    layout = texel_layout(obs, (4, 4))
    pairs = neighbour_pairs((4, 4))
    return Problem(obs, layout.index, layout.weight, jnp.ones((16, 5)), jnp.asarray(pairs),
                   jnp.ones(len(pairs)), jnp.asarray(0.0), jnp.asarray(0.05), None, Model(), "l2")


def test_per_pixel_integrals():
    env = procedural_sky(16)
    n = jnp.tile(jnp.array([[0.0, 1.0, 0.0]]), (4, 1))
    for model in (Model(), Model(fresnel="dielectric", diffuse="burley", multiscatter=True)):
        _check(lambda nn: integrate_lobes(env, jnp.zeros((64, 64, 2)), nn, nn, jnp.uint32(0), jnp.uint32(0), model=model,
                                           lobes=lobes_for(model), levels=3, samples=4, batch=2), n)


@pytest.mark.parametrize("per_pixel", [False, True])
def test_fitting(per_pixel):
    problem = _problem()
    if per_pixel:
        model = Model(ibl="per_pixel")
        problem = dataclasses.replace(problem, ibl=_zero_table(problem.obs.num_pixels, model), model=model)
    x0 = jnp.full((16, 5), 0.5)
    _check(solve, x0, problem, StructuredLM(), jnp.asarray(3))
    _check(grid_initialise, x0, problem)
    _check(coordinate_search, x0, problem, jnp.asarray(parity_classes((4, 4))))
    for name in OPTX_SOLVERS:
        _check(optx_solve, x0, problem, make_solver(name, 1e-6, 1e-6), 3)
    # after the solve: the normal matrix's blocks of the uncertainty windows and the uniform
    # check's profile curvature (lowering reads only the shapes of the residuals and Jacobians)
    r, jac = (jnp.zeros(a.shape, a.dtype) for a in jax.eval_shape(linearize, x0, problem)[:2])
    _check(normal_blocks, jac, problem)
    _check(lambda j, p: neighbour_blocks(j, p, (4, 4)), jac, problem)
    directions = jnp.stack([jnp.asarray(uniform_direction(np.ones(16, bool), c, 5)) for c in (3, 4)])
    _check(profile_hessian, r, jac, x0, problem, directions)

