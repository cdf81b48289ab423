"""Clamps whose derivative at a bound is the one from inside.

``jnp.clip``, ``jnp.maximum`` and ``jnp.minimum`` split the derivative between their arguments at
a tie: a value exactly on a bound gets half of it, and a quarter through two. A fit holds values
on bounds (a roughness on the fit's floor, a metal's black channel under a flash, a cosine at the
end of its domain), and there Gauss-Newton steps and standard errors came out two to four times
too large. `clamp_inward` is the clamp of the shading chain: `pbrfit.physics.brdf`, `pbrfit.physics.color`, the
material's [0, 1] range in `pbrfit.render.shade` and the IBL lookups.
"""

from __future__ import annotations

from typing import Optional

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["clamp_inward"]


def clamp_inward(x: Float[ArrayLike, "*batch"], lo: float, hi: Optional[float] = None) -> Float[Array, "*batch"]:
    """min(max(x, lo), hi) whose derivative at x = lo and x = hi is 1, the one-sided derivative
    from inside (0 outside the bounds, as a clamp's). jnp.maximum and jnp.clip give 1/2 at a tie,
    so a roughness held on a bound of the fit's box (`pbrfit.fitting.parameters`: MIN_ROUGHNESS, 1) had a
    half (at 1) or a quarter (at the floor, through two floors) of its Jacobian column."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):  # an integer roughness too: the floor is not an integer
        x = x.astype(jnp.result_type(float))
    # the bounds as Python numbers: weakly typed, so a Python-float x stays weak as under jnp.clip
    # (with x64 on, a float32 array beside it keeps float32)
    out = jnp.where(x < lo, float(lo), x)
    return out if hi is None else jnp.where(x > hi, float(hi), out)
