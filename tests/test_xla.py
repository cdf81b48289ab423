"""`pbrfit.xla`: compiling with the options pbrfit chooses, and with XLA's defaults where a build
does not know them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit import xla


def test_compile_lowered_uses_the_options_and_falls_back_on_unknown_ones():
    lowered = jax.jit(lambda v: jnp.sin(v) * 2.0).lower(jnp.arange(4.0))
    want = np.sin(np.arange(4.0)) * 2.0
    np.testing.assert_allclose(xla.compile_lowered(lowered, xla.FAST_COMPILE)(jnp.arange(4.0)), want, rtol=1e-6)
    np.testing.assert_allclose(xla.compile_lowered(lowered, {"no_such_option": True})(jnp.arange(4.0)), want, rtol=1e-6)
    with pytest.raises(Exception, match="not a valid int32"):  # a known option's wrong value is the caller's error
        xla.compile_lowered(lowered, {"xla_backend_optimization_level": "high"})


def test_jit_choosing_runs_the_fast_compile_where_asked(monkeypatch):
    f = xla.jit_choosing(lambda v: v * v, lambda args: args[0].shape[0] < 4)
    np.testing.assert_array_equal(f(jnp.arange(3.0)), [0.0, 1.0, 4.0])
    np.testing.assert_array_equal(f(jnp.arange(5.0)), [0.0, 1.0, 4.0, 9.0, 16.0])
    full, fast = f.variants
    assert fast._cache_size() == 1 and full._cache_size() == 1  # one shape each
    # inside another program (whose compile options hold for all of it): the plain one
    np.testing.assert_array_equal(jax.jit(lambda v: f(v) + 1.0)(jnp.arange(2.0)), [1.0, 2.0])
    assert fast._cache_size() == 1
    monkeypatch.setattr(xla, "FAST_COMPILE", {"no_such_option": True})  # an XLA without the option
    g = xla.jit_choosing(lambda v: v + 1.0, lambda args: True)
    np.testing.assert_array_equal(g(jnp.arange(3.0)), [1.0, 2.0, 3.0])
    assert g.variants[0]._cache_size() == 1
