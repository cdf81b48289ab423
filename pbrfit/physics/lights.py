"""Punctual lights with glTF ``KHR_lights_punctual`` semantics and units.

A light is a small pytree (`Light`); `incident` gives, for a batch of surface points, the unit
direction towards the light and the radiance-like quantity a BRDF·cos multiplies:

* point and spot: ``E = color * intensity * window(d) * spot(cd) / d^2`` with ``intensity`` in
  candela (lm/sr), so ``E`` is the irradiance on a surface facing the light, in lux;
* directional: ``E = color * intensity``, ``intensity`` already in lux.

``direction`` is where the light travels (a spot's axis, a sun's rays), as in
KHR_lights_punctual, where a light shines down its node's -Z axis.

Range window (glTF-Sample-Viewer ``getRangeAttenuation``, as KHR_lights_punctual recommends;
Karis 2013 squares it and divides by d² + 1 instead):
``window(d) = clamp(1 - (d / range)^4, 0, 1)`` when ``range > 0``, else 1; the ``1/d^2`` stays
outside the window. Spot falloff (the KHR_lights_punctual reference code, as glTF-Sample-Viewer's
``getSpotAttenuation``): ``cd = dot(spot_direction, -l)``,
``spot = clamp((cd - cos(outer)) / (cos(inner) - cos(outer)), 0, 1)^2``.

Every function here is pure ``jnp`` and jittable; ``kind`` is static, so a jitted function
specialises on the light type.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..transfer import to_device

__all__ = [
    "KINDS",
    "MIN_DISTANCE",
    "SPOT_MIN_COS_DELTA",
    "DEFAULT_INNER_CONE_ANGLE",
    "DEFAULT_OUTER_CONE_ANGLE",
    "Light",
    "point_light",
    "spot_light",
    "directional_light",
    "flash_light",
    "incident",
    "range_window",
    "spot_falloff",
]

KINDS = ("point", "spot", "directional")

# The distance below which a point light is treated as this far away: keeps 1/d^2 and the
# direction l = (p_light - p) / d finite when a surface point sits on the light (a flash at a
# camera inside the mesh, a test grid through the light). 1e-4 world units: far below any
# capture's scale, far above float32's underflow of d^2 (~1e-38).
MIN_DISTANCE = 1e-4

# Floor of cos(inner) - cos(outer) in the spot falloff: KHR_lights_punctual's reference
# implementation uses the same 0.001 so that inner == outer (a hard-edged spot) stays finite.
SPOT_MIN_COS_DELTA = 1e-3

# KHR_lights_punctual defaults for spot.innerConeAngle and spot.outerConeAngle.
DEFAULT_INNER_CONE_ANGLE = 0.0
DEFAULT_OUTER_CONE_ANGLE = math.pi / 4.0


class Light(eqx.Module):
    """One punctual light. Unused fields hold zeros (a point light's ``direction``).

    Attributes:
        kind: ``"point"``, ``"spot"`` or ``"directional"`` (static under jit).
        position: (3,) world position (point, spot).
        direction: (3,) unit vector, where the light travels (spot, directional).
        color: (3,) linear RGB.
        intensity: () candela for point and spot, lux for directional.
        range: () distance cutoff of the window; 0 means infinite (point, spot).
        inner_cone_angle, outer_cone_angle: () radians (spot).
    """

    kind: str = eqx.field(static=True)
    position: Float[Array, "3"]
    direction: Float[Array, "3"]
    color: Float[Array, "3"]
    intensity: Float[Array, ""]
    range: Float[Array, ""]
    inner_cone_angle: Float[Array, ""]
    outer_cone_angle: Float[Array, ""]


def _on_host(*xs) -> bool:
    """Whether every leaf of `xs` is a host value (numbers, lists, numpy), none a device array or
    a tracer: then a light is built in numpy and handed over whole, compiling no eager kernels."""
    return not any(isinstance(leaf, jax.Array) for leaf in jax.tree_util.tree_leaves(xs))


def _vec3(x) -> Float[Array, "3"]:
    if _on_host(x):
        return to_device(np.asarray(x, np.float32).reshape(3))
    return jnp.asarray(x, dtype=jnp.float32).reshape(3)


def _scalar(x) -> Float[Array, ""]:
    if _on_host(x):
        return to_device(np.asarray(x, np.float32).reshape(()))
    return jnp.asarray(x, dtype=jnp.float32).reshape(())


def _unit(x) -> Float[Array, "3"]:
    if _on_host(x):
        v = np.asarray(x, np.float64).reshape(3)
        n = float(np.linalg.norm(v))
        return to_device((v / n if n > 0 else v).astype(np.float32))
    v = _vec3(x)
    n2 = jnp.sum(v * v)
    safe = jnp.where(n2 > 0, n2, 1.0)
    return jnp.where(n2 > 0, v / jnp.sqrt(safe), v)


def point_light(position, color=(1.0, 1.0, 1.0), intensity=1.0, range=0.0) -> Light:
    """A point light at ``position``; ``intensity`` in candela; ``range`` 0 = infinite."""
    return Light(
        kind="point",
        position=_vec3(position),
        direction=to_device(np.zeros(3, np.float32)),
        color=_vec3(color),
        intensity=_scalar(intensity),
        range=_scalar(range),
        inner_cone_angle=_scalar(0.0),
        outer_cone_angle=_scalar(0.0),
    )


def spot_light(
    position,
    direction,
    color=(1.0, 1.0, 1.0),
    intensity=1.0,
    range=0.0,
    inner_cone_angle=DEFAULT_INNER_CONE_ANGLE,
    outer_cone_angle=DEFAULT_OUTER_CONE_ANGLE,
) -> Light:
    """A spot light at ``position`` shining along ``direction`` (normalised here)."""
    return Light(
        kind="spot",
        position=_vec3(position),
        direction=_unit(direction),
        color=_vec3(color),
        intensity=_scalar(intensity),
        range=_scalar(range),
        inner_cone_angle=_scalar(inner_cone_angle),
        outer_cone_angle=_scalar(outer_cone_angle),
    )


def directional_light(direction, color=(1.0, 1.0, 1.0), intensity=1.0) -> Light:
    """A directional light whose rays travel along ``direction``; ``intensity`` in lux."""
    return Light(
        kind="directional",
        position=to_device(np.zeros(3, np.float32)),
        direction=_unit(direction),
        color=_vec3(color),
        intensity=_scalar(intensity),
        range=_scalar(0.0),
        inner_cone_angle=_scalar(0.0),
        outer_cone_angle=_scalar(0.0),
    )


def flash_light(c2w, color=(1.0, 1.0, 1.0), intensity=1.0, offset=(0.0, 0.0, 0.0)) -> Light:
    """A camera flash: a point light at the camera centre plus ``offset`` in camera space.

    ``position = c2w[:3, 3] + c2w[:3, :3] @ offset`` (OpenGL camera axes: +X right, +Y up,
    the camera looks down -Z).
    """
    if _on_host(c2w, offset):  # a capture's cameras: numpy, no eager kernels
        m = np.asarray(c2w, np.float64).reshape(4, 4)
        position = m[:3, 3] + m[:3, :3] @ np.asarray(offset, np.float64).reshape(3)
    else:
        m = jnp.asarray(c2w, dtype=jnp.float32).reshape(4, 4)
        position = m[:3, 3] + m[:3, :3] @ _vec3(offset)
    return point_light(position, color, intensity, 0.0)


def range_window(d: Float[Array, "*batch"], range_: Float[Array, ""]) -> Float[Array, "*batch"]:
    """``clamp(1 - (d/range)^4, 0, 1)`` for ``range > 0``, else 1 (glTF-Sample-Viewer)."""
    positive = range_ > 0
    safe_range = jnp.where(positive, range_, 1.0)
    w = jnp.clip(1.0 - (d / safe_range) ** 4, 0.0, 1.0)
    return jnp.where(positive, w, jnp.ones_like(w))


def spot_falloff(
    cd: Float[Array, "*batch"], inner: Float[Array, ""], outer: Float[Array, ""]
) -> Float[Array, "*batch"]:
    """``t^2`` with ``t = clamp((cd - cos(outer)) / (cos(inner) - cos(outer)), 0, 1)`` and
    ``cd = dot(spot_direction, -l)``.

    The KHR_lights_punctual reference code ("Inner and Outer Cone Angles": ``lightAngleScale``,
    ``lightAngleOffset``, then ``angularAttenuation *= angularAttenuation``), which
    glTF-Sample-Viewer's ``getSpotAttenuation`` implements: 0 outside the outer cone, 1 inside the
    inner, a steep decline leveling off towards the outer cone between.
    ``cos(inner) - cos(outer)`` is floored at `SPOT_MIN_COS_DELTA`, as in the reference code, so
    that a hard-edged cone stays finite.
    """
    cos_outer = jnp.cos(outer)
    cos_inner = jnp.cos(inner)
    delta = jnp.maximum(cos_inner - cos_outer, SPOT_MIN_COS_DELTA)
    t = jnp.clip((cd - cos_outer) / delta, 0.0, 1.0)
    return t * t


def incident(
    light: Light, points: Float[ArrayLike, "*P 3"]
) -> tuple[Float[Array, "*P 3"], Float[Array, "*P 3"]]:
    """Light arriving at ``points``: ``(l, E)``.

    ``l`` (*P, 3) is the unit direction from the surface point towards the light; ``E`` (*P, 3)
    is ``color * intensity * window(d) * spot / d^2`` for point and spot lights (lux) and
    ``color * intensity`` for directional lights. ``d`` is floored at `MIN_DISTANCE`, so both
    outputs and their gradients are finite everywhere (within `MIN_DISTANCE` of the light l is
    shorter than 1, and a point on the light gets l = 0).
    """
    points = jnp.asarray(points)
    dtype = jnp.result_type(points.dtype, jnp.float32)
    points = points.astype(dtype)
    color = light.color.astype(dtype)
    intensity = light.intensity.astype(dtype)
    if light.kind == "directional":
        l = jnp.broadcast_to(-light.direction.astype(dtype), points.shape)
        e = jnp.broadcast_to(color * intensity, points.shape)
        return l, e
    if light.kind not in ("point", "spot"):
        raise ValueError(f"unknown light kind {light.kind!r}")
    to_light = light.position.astype(dtype) - points
    d2 = jnp.sum(to_light * to_light, axis=-1)
    d2_safe = jnp.maximum(d2, MIN_DISTANCE**2)
    d = jnp.sqrt(d2_safe)
    l = to_light / d[..., None]
    scale = range_window(d, light.range.astype(dtype)) / d2_safe
    if light.kind == "spot":
        cd = jnp.sum(light.direction.astype(dtype) * (-l), axis=-1)
        scale = scale * spot_falloff(
            cd, light.inner_cone_angle.astype(dtype), light.outer_cone_angle.astype(dtype)
        )
    e = (color * intensity) * scale[..., None]
    return l, e
