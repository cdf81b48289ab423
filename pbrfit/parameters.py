"""Fitted material parameters: the five channels, their bounds, and the maps to and from storage.

A texel holds five numbers, in this order everywhere in the fit (and in ``uncertainty.exr``):
base colour R, G, B (linear), metallic, perceptual roughness. Their bounds are

    base colour, metallic in [0, 1];   roughness in [MIN_ROUGHNESS, 1]

(`pbrfit.brdf.MIN_ROUGHNESS`: below it the BRDF clamps, so the images cannot tell values apart).

Two storages, chosen per solver:

- **Box-projected** (the default structured solver): the bounded values themselves. Each
  Gauss-Newton step is solved with the channels that sit on a bound and are pushed outwards held
  fixed (the active set), and the iterate is clipped back into the box. A texel whose truth is
  metallic 0 or 1 lands on the bound exactly, in finitely many steps.
- **Sine** (the general optimistix solvers, which know nothing of bounds): unconstrained ``z``
  with ``value = lo + (hi - lo) (1 + sin z) / 2``. Unlike the logistic sigmoid, the bounds are
  reached at finite ``z = ±π/2`` (a sigmoid needs ``z -> ±∞`` and stalls: its derivative
  vanishes exponentially on the way), and the map is periodic, so no value of ``z`` is out of
  range. Its derivative is zero exactly at a bound, which damped solvers tolerate.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .brdf import MIN_ROUGHNESS

__all__ = [
    "CHANNELS",
    "FIT_GROUPS",
    "LOWER",
    "UPPER",
    "PRIOR",
    "channel_mask",
    "clip_to_bounds",
    "to_sine",
    "from_sine",
]

#: The five fitted channels, in storage order.
CHANNELS = ("base_r", "base_g", "base_b", "metallic", "roughness")
#: User-facing names (``fit=`` / ``--fit``) and the channels each frees.
FIT_GROUPS = {"base_color": (0, 1, 2), "metallic": (3,), "roughness": (4,)}
#: Lower bounds per channel. Roughness stops at the BRDF's floor: below it values are identical.
LOWER = np.array([0.0, 0.0, 0.0, 0.0, MIN_ROUGHNESS], np.float32)
#: Upper bounds per channel.
UPPER = np.array([1.0, 1.0, 1.0, 1.0, 1.0], np.float32)
#: Where a texel starts, and where it stays when no view sees it: mid-grey, dielectric, mid rough.
PRIOR = np.array([0.5, 0.5, 0.5, 0.0, 0.5], np.float32)


def channel_mask(fit: tuple[str, ...] | list[str]) -> np.ndarray:
    """(5,) float32: 1 for channels the named groups free, 0 for fixed ones."""
    mask = np.zeros(5, np.float32)
    for name in fit:
        if name not in FIT_GROUPS:
            raise ValueError(f"unknown fitted map {name!r}; expected some of {', '.join(FIT_GROUPS)}")
        mask[list(FIT_GROUPS[name])] = 1.0
    return mask


def clip_to_bounds(x: Float[ArrayLike, "... 5"]) -> Float[Array, "... 5"]:
    """Project texel values into the box [LOWER, UPPER]."""
    return jnp.clip(x, jnp.asarray(LOWER, jnp.result_type(x)), jnp.asarray(UPPER, jnp.result_type(x)))


def from_sine(z: Float[ArrayLike, "... 5"], channels=slice(None)) -> Float[Array, "... 5"]:
    """Bounded values from unconstrained storage: lo + (hi - lo) (1 + sin z) / 2."""
    lo = jnp.asarray(LOWER[channels])
    hi = jnp.asarray(UPPER[channels])
    return lo + (hi - lo) * 0.5 * (1.0 + jnp.sin(z))


def to_sine(x: Float[ArrayLike, "... 5"], channels=slice(None)) -> Float[Array, "... 5"]:
    """The storage ``z`` in [-π/2, π/2] of bounded values (inverse of `from_sine` on that branch)."""
    lo = jnp.asarray(LOWER[channels])
    hi = jnp.asarray(UPPER[channels])
    t = jnp.clip(2.0 * (jnp.asarray(x) - lo) / (hi - lo) - 1.0, -1.0, 1.0)
    return jnp.arcsin(t)
