"""`pbrfit.transfer.to_device`: values and dtypes arrive unchanged, and nothing is compiled."""

import logging

import jax
import numpy as np

from pbrfit.transfer import to_device


def test_to_device_converts_in_numpy_and_compiles_nothing(caplog):
    rng = np.random.default_rng(0)
    x64 = rng.random((37, 4, 3))  # float64 on the host, a shape no test used before
    with jax.log_compiles(True), caplog.at_level(logging.WARNING):
        a = to_device(x64, np.float32)
        b = to_device(np.arange(11), np.int32)
        c = to_device(0.25, np.float32)
    assert not [r for r in caplog.records if "Compiling" in r.getMessage()]
    assert isinstance(a, jax.Array) and a.dtype == np.float32 and a.shape == (37, 4, 3)
    np.testing.assert_array_equal(np.asarray(a), x64.astype(np.float32))
    assert b.dtype == np.int32 and np.asarray(b).tolist() == list(range(11))
    assert c.shape == () and float(c) == 0.25
