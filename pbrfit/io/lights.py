"""Punctual lights as ``capture.json`` holds them (KHR_lights_punctual's keys and units):
`light_from_json` reads and checks one, naming the key of every error; `light_to_json` writes one.
The lights themselves are `pbrfit.physics.lights`.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from ..errors import CaptureError
from ..physics.lights import (DEFAULT_INNER_CONE_ANGLE, DEFAULT_OUTER_CONE_ANGLE, KINDS, Light, directional_light,
                              point_light, spot_light)
from .json_fields import field_loc, number_field, triple_field

__all__ = ["color_and_intensity", "light_from_json", "light_to_json"]

# A direction shorter than this cannot be normalised.
_MIN_DIRECTION_NORM = 1e-12
_COMMON_KEYS = ("type", "name", "color", "intensity", "extras")
_ALLOWED_KEYS = {
    "point": _COMMON_KEYS + ("position", "range"),
    "spot": _COMMON_KEYS + ("position", "direction", "range", "inner_cone_angle", "outer_cone_angle"),
    # `range` on a directional light is checked and ignored (some writers emit it for every light)
    "directional": _COMMON_KEYS + ("direction", "range"),
}


def _direction(d: Mapping[str, Any], where: str) -> np.ndarray:
    v = triple_field(d, "direction", where)
    if np.linalg.norm(v) < _MIN_DIRECTION_NORM:
        raise CaptureError(f"{field_loc(where, 'direction')}: zero vector has no direction")
    return v


def color_and_intensity(d: Mapping[str, Any], where: str) -> tuple[np.ndarray, float]:
    """A light object's ``color`` (default white) and ``intensity`` (default 1), both >= 0."""
    color = triple_field(d, "color", where, (1.0, 1.0, 1.0))
    if np.any(color < 0):
        raise CaptureError(f"{field_loc(where, 'color')}: negative color {d['color']!r}")
    intensity = number_field(d, "intensity", where, 1.0)
    if intensity < 0:
        raise CaptureError(f"{field_loc(where, 'intensity')}: negative intensity {intensity!r}")
    return color, intensity


def light_from_json(d: Any, where: str) -> Light:
    """Build a `Light` from its capture.json object, validating every key.

    ``where`` names the object in messages (``"capture.json: lights[2]"``). Raises
    `CaptureError` for a non-object, an unknown ``type``, an unknown key, a missing position or
    direction, a negative intensity or range, bad cone angles (KHR_lights_punctual:
    0 <= inner < outer <= pi/2) or a zero direction. A directional light's ``range`` is checked
    and ignored (KHR_lights_punctual defines it for point and spot lights; exporters write it for
    every light). Defaults: color white, intensity 1, range 0 (infinite), cones 0 and pi/4 (KHR
    defaults)."""
    if not isinstance(d, Mapping):
        raise CaptureError(f"{where}: expected a light object, got {type(d).__name__}")
    if "type" not in d:
        raise CaptureError(f"{where}: missing key 'type' (one of {', '.join(KINDS)})")
    kind = d["type"]
    if kind not in KINDS:
        raise CaptureError(f"{field_loc(where, 'type')}: unknown light type {kind!r} (expected one of {', '.join(KINDS)})")
    allowed = _ALLOWED_KEYS[kind]
    for key in d:
        if key not in allowed:
            raise CaptureError(
                f"{where}: unknown key {key!r} for a {kind} light (allowed: {', '.join(allowed)})"
            )
    color, intensity = color_and_intensity(d, where)
    range_ = number_field(d, "range", where, 0.0)
    if range_ < 0:
        raise CaptureError(f"{field_loc(where, 'range')}: negative range {range_!r} (0 means infinite)")
    if kind == "directional":  # KHR_lights_punctual: range is for point and spot lights only, unused here
        return directional_light(_direction(d, where), color, intensity)
    position = triple_field(d, "position", where)
    if kind == "point":
        return point_light(position, color, intensity, range_)
    inner = number_field(d, "inner_cone_angle", where, DEFAULT_INNER_CONE_ANGLE)
    outer = number_field(d, "outer_cone_angle", where, DEFAULT_OUTER_CONE_ANGLE)
    if not (0.0 <= inner < outer <= math.pi / 2 + 1e-9):
        raise CaptureError(
            f"{where}: cone angles must satisfy 0 <= inner_cone_angle < outer_cone_angle <= pi/2, "
            f"got {inner!r} and {outer!r}"
        )
    return spot_light(position, _direction(d, where), color, intensity, range_, inner, outer)


def light_to_json(light: Light) -> dict:
    """The capture.json object of ``light`` (inverse of `light_from_json`)."""

    def vec(x) -> list[float]:
        return [float(v) for v in np.asarray(x, dtype=np.float64).reshape(3)]

    out: dict[str, Any] = {"type": light.kind}
    if light.kind in ("point", "spot"):
        out["position"] = vec(light.position)
    if light.kind in ("spot", "directional"):
        out["direction"] = vec(light.direction)
    out["color"] = vec(light.color)
    out["intensity"] = float(light.intensity)
    if light.kind in ("point", "spot"):
        out["range"] = float(light.range)
    if light.kind == "spot":
        out["inner_cone_angle"] = float(light.inner_cone_angle)
        out["outer_cone_angle"] = float(light.outer_cone_angle)
    return out
