"""Host arrays to the device without compiling anything.

`jnp.asarray(numpy_array)` compiles a small copy kernel (``jit(stage)``) for every new shape, and
a dtype change on the way in another (``convert_element_type``); in a fit's setup, with one shape
per view and per map, those add up to most of a second of XLA compilation. `to_device` converts
the dtype in numpy and hands the buffer to `jax.device_put`, which compiles nothing.
"""

from __future__ import annotations

from typing import Any, Optional

import jax
import numpy as np

__all__ = ["to_device"]


def to_device(x: Any, dtype: Optional[Any] = None) -> jax.Array:
    """`x` (a numpy array, a scalar or a nested sequence) as a device array of `dtype` (default:
    numpy's dtype for it), placed on the default device."""
    return jax.device_put(np.asarray(x, dtype=dtype))
