"""Fitted material parameters: the channels, their bounds, and the maps to and from storage.

A texel holds five numbers, in this order everywhere in the fit (and in ``uncertainty.exr``):
base colour R, G, B (linear), metallic, perceptual roughness; and, when normals are fitted, two
more: the tangent-space normal as slopes (s_x, s_y), n_ts = normalize(s_x, s_y, 1). Bounds:

    base colour, metallic in [0, 1];   roughness in [MIN_ROUGHNESS, 1];
    s_x, s_y in [-NORMAL_SLOPE_MAX, NORMAL_SLOPE_MAX]

(`pbrfit.physics.brdf.MIN_ROUGHNESS`: below it the BRDF clamps, so the images cannot tell values apart).
Slopes are unbounded in principle and zero for a flat map; every (s_x, s_y) is a valid normal,
unlike (n_x, n_y) with n_z = sqrt(1 - n_x² - n_y²), whose derivative blows up at the horizon.
Bilinear filtering in the fit interpolates slopes, a glTF viewer interpolates the unit vectors:
the two agree at texel centres and, between them, to first order in the slope difference.

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

from ..physics.brdf import MIN_ROUGHNESS

__all__ = [
    "CHANNELS",
    "NORMAL_CHANNELS",
    "NORMAL_SLOPE_MAX",
    "HORIZON_Z",
    "lower",
    "upper",
    "prior",
    "normal_from_slopes",
    "slopes_from_normal",
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
#: The two extra channels when normals are fitted: tangent-space slopes.
NORMAL_CHANNELS = ("normal_sx", "normal_sy")
#: User-facing names (``fit=`` / ``--fit``) and the channels each frees.
FIT_GROUPS = {"base_color": (0, 1, 2), "metallic": (3,), "roughness": (4,), "normal": (5, 6)}
#: Largest fitted slope: a normal tilted up to atan(4) = 76° from the surface normal.
NORMAL_SLOPE_MAX = 4.0
#: Floor on n_z in `slopes_from_normal`: only keeps the division finite for normals at or below
#: the horizon, whose slopes the clip to ±NORMAL_SLOPE_MAX then bounds.
HORIZON_Z = 1e-6
#: Lower bounds per channel. Roughness stops at the BRDF's floor: below it values are identical.
LOWER = np.array([0.0, 0.0, 0.0, 0.0, MIN_ROUGHNESS], np.float32)
#: Upper bounds per channel.
UPPER = np.array([1.0, 1.0, 1.0, 1.0, 1.0], np.float32)
#: Where a texel starts, and where it stays when no view sees it: mid-grey, dielectric, mid rough.
PRIOR = np.array([0.5, 0.5, 0.5, 0.0, 0.5], np.float32)


def lower(k: int = 5) -> np.ndarray:
    """(k,) lower bounds of the first k channels (k = 5, or 7 with normals)."""
    return np.concatenate([LOWER, np.full(2, -NORMAL_SLOPE_MAX, np.float32)])[:k]


def upper(k: int = 5) -> np.ndarray:
    """(k,) upper bounds of the first k channels."""
    return np.concatenate([UPPER, np.full(2, NORMAL_SLOPE_MAX, np.float32)])[:k]


def prior(k: int = 5) -> np.ndarray:
    """(k,) starting / unobserved values of the first k channels (flat normals)."""
    return np.concatenate([PRIOR, np.zeros(2, np.float32)])[:k]


def normal_from_slopes(s: Float[ArrayLike, "... 2"]) -> Float[Array, "... 3"]:
    """Unit tangent-space normals normalize(s_x, s_y, 1) (+Y / OpenGL convention)."""
    s = jnp.asarray(s)
    n = jnp.concatenate([s, jnp.ones_like(s[..., :1])], axis=-1)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


def slopes_from_normal(n: Float[ArrayLike, "... 3"]) -> Float[Array, "... 2"]:
    """Slopes (n_x / n_z, n_y / n_z) of tangent-space normals, clipped to ±NORMAL_SLOPE_MAX."""
    n = jnp.asarray(n)
    z = jnp.maximum(n[..., 2:3], HORIZON_Z)
    return jnp.clip(n[..., :2] / z, -NORMAL_SLOPE_MAX, NORMAL_SLOPE_MAX)


def channel_mask(fit: tuple[str, ...] | list[str]) -> np.ndarray:
    """(k,) float32: 1 for channels the named groups free, 0 for fixed ones; k = 7 when
    "normal" is among them, else 5."""
    mask = np.zeros(7 if "normal" in fit else 5, np.float32)
    for name in fit:
        if name not in FIT_GROUPS:
            raise ValueError(f"unknown fitted map {name!r}; expected some of {', '.join(FIT_GROUPS)}")
        mask[list(FIT_GROUPS[name])] = 1.0
    return mask


def clip_to_bounds(x: Float[ArrayLike, "... K"]) -> Float[Array, "... K"]:
    """Project texel values (5 or 7 channels) into the box [lower, upper]."""
    k = jnp.shape(x)[-1]
    return jnp.clip(x, jnp.asarray(lower(k), jnp.result_type(x)), jnp.asarray(upper(k), jnp.result_type(x)))


def from_sine(z: Float[ArrayLike, "... K"]) -> Float[Array, "... K"]:
    """Bounded values from unconstrained storage: lo + (hi - lo) (1 + sin z) / 2 (the bounds in
    z's precision, so that float64 reaches them exactly)."""
    z = jnp.asarray(z)
    k = jnp.shape(z)[-1]
    dtype = jnp.result_type(z, jnp.float32)
    lo = jnp.asarray(lower(k), dtype)
    hi = jnp.asarray(upper(k), dtype)
    return lo + (hi - lo) * 0.5 * (1.0 + jnp.sin(z))


def to_sine(x: Float[ArrayLike, "... K"]) -> Float[Array, "... K"]:
    """The storage ``z`` in [-π/2, π/2] of bounded values (inverse of `from_sine` on that branch).
    Its derivative is infinite at the bounds (arcsin's at ±1), where `from_sine`'s is 0: the
    optimistix solvers start inside them (`pbrfit.fitting.solvers.optx.START_MARGIN`)."""
    x = jnp.asarray(x)
    k = jnp.shape(x)[-1]
    dtype = jnp.result_type(x, jnp.float32)
    lo = jnp.asarray(lower(k), dtype)
    hi = jnp.asarray(upper(k), dtype)
    t = jnp.clip(2.0 * (x - lo) / (hi - lo) - 1.0, -1.0, 1.0)
    return jnp.arcsin(t)
