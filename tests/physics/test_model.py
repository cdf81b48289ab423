"""`pbrfit.physics.model.Model`: validation, hashing, static use under jit, and what each switch turns off."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit import brdf
from pbrfit.physics.model import DIFFUSES, DISTRIBUTIONS, FRESNELS, GEOMETRIES, IBLS, Model


@pytest.mark.parametrize("field", ["distribution", "geometry", "fresnel", "diffuse", "ibl"])
def test_unknown_variant_raises_naming_the_field(field):
    with pytest.raises(ValueError, match=rf"Model\.{field} 'nonsense'"):
        Model(**{field: "nonsense"})
    with pytest.raises(ValueError, match=rf"Model\.{field}"):
        Model().replace(**{field: "nonsense"})


def test_bad_flags_and_ior_raise():
    with pytest.raises(ValueError, match="Model.specular"):
        Model(specular=1)
    for bad in (0.5, float("inf"), float("nan"), True, "1.5"):
        with pytest.raises(ValueError, match="Model.ior"):
            Model(ior=bad)
    model = Model(ior=np.float32(1.33))  # a numpy scalar is a number: kept as a plain float
    assert type(model.ior) is float and model == Model(ior=float(np.float32(1.33))) and hash(model)


def test_every_listed_variant_constructs():
    for d in DISTRIBUTIONS:
        for g in GEOMETRIES:
            for f in FRESNELS:
                for diff in DIFFUSES:
                    for ibl in IBLS:
                        fields = dict(distribution=d, geometry=g, fresnel=f, diffuse=diff, ibl=ibl)
                        described = Model(**fields).describe()
                        assert {k: described[k] for k in fields} == fields


def test_hashable_and_equal_by_value():
    a, b = Model(diffuse="burley"), Model(diffuse="burley")
    assert a == b and hash(a) == hash(b)
    assert a != Model()
    assert {a: 1}[b] == 1
    assert Model().describe()["distribution"] == "ggx"


_N = jnp.array([0.0, 0.0, 1.0])
_V = jnp.array([0.6, 0.0, 0.8])
_MIRROR = jnp.array([-0.6, 0.0, 0.8])  # l = reflect(v, n): n·h = 1, the highlight
_AWAY = jnp.array([0.0, -0.6, 0.8])


@jax.jit
def _eval_default(l, base, metallic, roughness):
    return brdf.evaluate(_N, _V, l, base, metallic, roughness)


_eval = jax.jit(lambda l, base, metallic, roughness, model: brdf.evaluate(_N, _V, l, base, metallic, roughness, model),
                static_argnums=4)


def test_static_jit_argument():
    base = jnp.array([0.8, 0.5, 0.2])
    a = _eval(_MIRROR, base, 0.0, 0.5, Model())
    b = _eval(_MIRROR, base, 0.0, 0.5, Model(diffuse="burley"))
    np.testing.assert_allclose(a, _eval_default(_MIRROR, base, 0.0, 0.5), rtol=1e-6)
    assert not np.allclose(a, b)
    # an equal Model hits the compiled cache: same result, no retrace
    compiled = _eval._cache_size()
    np.testing.assert_array_equal(_eval(_MIRROR, base, 0.0, 0.5, Model(diffuse="burley")), b)
    assert _eval._cache_size() == compiled


def test_specular_off_leaves_no_highlight():
    base = jnp.array([0.9, 0.6, 0.3])
    # a white metal at its mirror highlight: the specular lobe is all there is
    assert np.all(np.asarray(_eval(_MIRROR, jnp.ones(3), 1.0, 0.1, Model(specular=False))) == 0.0)
    assert np.all(np.asarray(_eval(_MIRROR, jnp.ones(3), 1.0, 0.1, Model())) > 1.0)
    # a dielectric: Lambert alone, not weighted by (1 - F)
    out = _eval(_MIRROR, base, 0.0, 0.1, Model(specular=False))
    np.testing.assert_allclose(out, base / math.pi * 0.8, rtol=1e-6)


def test_diffuse_none_leaves_only_the_specular_lobe():
    base = jnp.array([0.9, 0.6, 0.3])
    r = 0.8
    out = np.asarray(_eval(_AWAY, base, 0.0, r, Model(diffuse="none")))
    full = np.asarray(_eval(_AWAY, base, 0.0, r, Model()))
    # the specular lobe from its terms, at this geometry
    h = (_V + _AWAY) / jnp.linalg.norm(_V + _AWAY)
    nh, vh = float(h[2]), float(h @ _V)
    a = r * r
    spec = brdf.f_schlick(vh, 0.04) * brdf.d_ggx(nh, a) * brdf.v_smith_ggx_correlated(0.8, 0.8, a) * 0.8
    np.testing.assert_allclose(out, np.full(3, float(spec)), rtol=1e-5)
    assert np.all(out < 0.1 * full)  # away from the highlight a rough dielectric is mostly diffuse
    # and a dielectric with neither lobe reflects nothing
    assert np.all(np.asarray(_eval(_AWAY, base, 0.0, r, Model(diffuse="none", specular=False))) == 0.0)


def test_metallic_off_ignores_metallic():
    base = jnp.array([0.9, 0.6, 0.3])
    a = _eval(_AWAY, base, 1.0, 0.5, Model(metallic=False))
    b = _eval(_AWAY, base, 0.0, 0.5, Model())
    np.testing.assert_allclose(a, b, rtol=1e-6)


def test_multiscatter_needs_dfg():
    with pytest.raises(ValueError, match="dfg"):
        brdf.evaluate(_N, _V, _MIRROR, jnp.ones(3), 1.0, 0.5, Model(multiscatter=True))
