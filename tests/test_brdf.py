"""Physics and numerical-stability checks of `pbrfit.brdf` (issue 2)."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit import brdf
from pbrfit.model import Model

# --- The acceptance grid of issue 2: closed domain, float32 ---------------------------------------
ROUGHNESS = (0.0, 1e-6, 1e-3, 0.05, 0.5, 1.0)
COSINES = (0.0, 1e-7, 1e-3, 0.5, 1.0)
BINARY = (0.0, 1.0)

#: Every variant value appears at least once; the product of all of them is 192 compiles, too many.
GRID_MODELS = (
    Model(),
    Model(distribution="beckmann"),
    Model(geometry="smith_ggx_separable"),
    Model(geometry="schlick_ggx_direct"),
    Model(geometry="schlick_ggx_ibl"),
    Model(fresnel="dielectric"),
    Model(fresnel="dielectric", metallic=False),
    Model(diffuse="burley"),
    Model(diffuse="none"),
    Model(specular=False),
    Model(distribution="beckmann", geometry="schlick_ggx_ibl", diffuse="burley", fresnel="dielectric"),
    Model(multiscatter=True),
)


def _cosine_grid() -> np.ndarray:
    """(N, 7) float32 rows (n·v, n·l, n·h, v·h, roughness, metallic, base color)."""
    rows = itertools.product(COSINES, COSINES, COSINES, COSINES, ROUGHNESS, BINARY, BINARY)
    return np.array(list(rows), dtype=np.float32)


def _cosine_inputs(p):
    nv, nl, nh, vh, r, m, b = (p[:, i] for i in range(7))
    base = jnp.stack([b, 0.5 * b + 0.25, b], axis=-1)  # one channel off the corners as well
    return nv, nl, nh, vh, base, m[:, None], r[:, None]


def _dfg_for(n):
    # A plausible split-sum (scale, bias) pair; the value is irrelevant to finiteness.
    return jnp.broadcast_to(jnp.array([0.7, 0.05], dtype=jnp.float32), (n, 2))


def _eval_cosines_sum(p, model):
    nv, nl, nh, vh, base, m, r = _cosine_inputs(p)
    dfg = _dfg_for(p.shape[0]) if model.multiscatter else None
    return brdf.evaluate_cosines(nv, nl, nh, vh, base, m, r, model, dfg)


_cosines_value_and_grad = jax.jit(
    lambda p, model: (_eval_cosines_sum(p, model), jax.grad(lambda q: _eval_cosines_sum(q, model).sum())(p)),
    static_argnums=1,
)


def _direction_grid() -> np.ndarray:
    """(N, 7) float32 rows (θ-cosines of v and l, azimuth between them, roughness, metallic, base)."""
    phis = (0.0, 0.5 * math.pi, math.pi)  # v·l from largest to smallest for given cosines
    rows = itertools.product(COSINES, COSINES, phis, ROUGHNESS, BINARY, BINARY)
    return np.array(list(rows), dtype=np.float32)


def _dir(cos_t, phi):
    s = jnp.sqrt(jnp.maximum(1.0 - cos_t * cos_t, 0.0))
    return jnp.stack([s * jnp.cos(phi), s * jnp.sin(phi), cos_t], axis=-1)


def _eval_vectors(p, model):
    cv, cl, phi, r, m, b = (p[:, i] for i in range(6))
    n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], dtype=p.dtype), (p.shape[0], 3))
    v = _dir(cv, jnp.zeros_like(phi))
    l = _dir(cl, phi)
    base = jnp.stack([b, 0.5 * b + 0.25, b], axis=-1)
    dfg = _dfg_for(p.shape[0]) if model.multiscatter else None
    return n, v, l, base, m, r, dfg


def _vectors_value_and_grad(p, model):
    n, v, l, base, m, r, dfg = _eval_vectors(p, model)

    def total(n, v, l, base, m, r):
        return brdf.evaluate(n, v, l, base, m, r, model, dfg).sum()

    value = brdf.evaluate(n, v, l, base, m, r, model, dfg)
    return value, jax.grad(total, argnums=(0, 1, 2, 3, 4, 5))(n, v, l, base, m, r)


_vectors_value_and_grad = jax.jit(_vectors_value_and_grad, static_argnums=1)


def _model_id(model: Model) -> str:
    d = Model().describe()
    changed = {k: v for k, v in model.describe().items() if d[k] != v}
    return ",".join(f"{k}={v}" for k, v in changed.items()) or "default"


def _report_bad(p, value, grads, names):
    bad_v = ~np.all(np.isfinite(value) & (value >= 0.0), axis=-1)
    msgs = []
    if bad_v.any():
        msgs.append(f"value non-finite or negative at {p[bad_v][:3].tolist()}")
    for name, g in zip(names, grads):
        g = np.asarray(g).reshape(p.shape[0], -1)
        bad = ~np.all(np.isfinite(g), axis=-1)
        if bad.any():
            msgs.append(f"d/d{name} non-finite at {int(bad.sum())} points, e.g. {p[bad][:3].tolist()}")
    return msgs


@pytest.mark.parametrize("model", GRID_MODELS, ids=_model_id)
def test_acceptance_grid_evaluate_cosines_float32(model):
    p = _cosine_grid()
    value, grad = _cosines_value_and_grad(jnp.asarray(p), model)
    value, grad = np.asarray(value), np.asarray(grad)
    names = ("n·v", "n·l", "n·h", "v·h", "roughness", "metallic", "base_color")
    msgs = _report_bad(p, value, [grad[:, i] for i in range(7)], names)
    assert not msgs, f"{_model_id(model)} (rows: n·v, n·l, n·h, v·h, roughness, metallic, base): " + "; ".join(msgs)


@pytest.mark.parametrize("model", GRID_MODELS, ids=_model_id)
def test_acceptance_grid_evaluate_float32(model):
    p = _direction_grid()
    value, grads = _vectors_value_and_grad(jnp.asarray(p), model)
    value = np.asarray(value)
    names = ("n", "v", "l", "base_color", "metallic", "roughness")
    msgs = _report_bad(p, value, grads, names)
    assert not msgs, f"{_model_id(model)} (rows: cos θv, cos θl, Δφ, roughness, metallic, base): " + "; ".join(msgs)


# --- Known traps, one test each -------------------------------------------------------------------
def test_trap_beckmann_gradient_at_grazing_half_vector_float32():
    """d_beckmann = exp(-tan²/α²) / (π α² cos⁴): the reverse pass of 1/(α² cos⁴) squares a ~1e-22
    denominator, which underflows in float32 and turns the exactly-zero value into 0 · inf = NaN."""
    for nh in (0.0, 1e-7, 1e-4):
        for alpha in (brdf.MIN_ALPHA, 0.0025):
            g = jax.grad(brdf.d_beckmann, argnums=(0, 1))(jnp.float32(nh), jnp.float32(alpha))
            assert all(np.isfinite(np.asarray(x)) for x in g), (nh, alpha, g)


def test_trap_beckmann_evaluate_lit_grazing_pair():
    """A lit pair (n·v = n·l = 1e-5, 90° apart in azimuth, so n·h ≈ 1.4e-5 < COS_MIN) at roughness 0."""
    c = 1e-5
    n = jnp.array([0.0, 0.0, 1.0])
    v = jnp.array([1.0, 0.0, c]) / math.sqrt(1 + c * c)
    l = jnp.array([0.0, 1.0, c]) / math.sqrt(1 + c * c)
    model = Model(distribution="beckmann")
    f = lambda b, m, r: brdf.evaluate(n, v, l, b, m, r, model).sum()
    grads = jax.grad(f, argnums=(0, 1, 2))(jnp.ones(3), jnp.float32(0.0), jnp.float32(0.0))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads), grads
