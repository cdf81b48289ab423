"""Fields of ``capture.json`` (and of a lights file) read and checked: each refusal a
`pbrfit.errors.CaptureError` naming the key (`field_loc`) and what is wrong. Numbers are JSON
numbers (bools and strings are not), finite and within float32's range, as the solve needs."""

from __future__ import annotations

import json
import math
import sys
from typing import Any, Mapping, Optional

import numpy as np

from ..errors import CaptureError

__all__ = ["JSONError", "parse_json", "FLOAT32_MAX", "field_loc", "shown", "as_float", "number_field", "triple_field", "positive_field",
           "string_field", "object_field", "check_keys", "without_nulls"]


class JSONError(ValueError):
    """A text that is not the JSON a capture holds; the message says where and why, in one line."""


def _unique_keys(pairs: list) -> dict:
    keys = {}
    for key, value in pairs:
        if key in keys:  # json.loads would keep the last one, without a word
            raise JSONError(f"invalid JSON: key {shown(key)} twice in one object")
        keys[key] = value
    return keys


def parse_json(text: str) -> Any:
    """``json.loads`` with every way a text can fail it as one `JSONError`: a syntax error (its line
    and column), a key twice in one object (which JSON leaves undefined and Python reads as the
    last), an integer past Python's limit on digits, nesting deeper than Python recurses."""
    try:
        return json.loads(text, object_pairs_hook=_unique_keys)
    except json.JSONDecodeError as err:
        raise JSONError(f"invalid JSON at line {err.lineno} column {err.colno}: {err.msg}") from None
    except RecursionError:
        raise JSONError("invalid JSON: nested too deeply") from None
    except JSONError:
        raise
    except ValueError:  # int("9" * 5000): "Exceeds the limit (4300 digits) for integer string conversion"
        raise JSONError(f"invalid JSON: an integer of more than {sys.get_int_max_str_digits()} digits") from None


def field_loc(where: str, key: str) -> str:
    """``where`` + ``key`` for messages: ``capture.json: flash`` + ``intensity`` gives
    ``capture.json: flash.intensity``; a bare json file name gives ``capture.json: intensity``."""
    return f"{where}: {key}" if where.endswith(".json") else f"{where}.{key}"


#: The largest magnitude a number of a capture may have: the solve runs in float32.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def shown(value, limit: int = 40) -> str:
    """``repr(value)`` for a message, cut to ``limit`` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_float(value, loc: str, what: str = "a finite number") -> float:
    """`value` (a JSON number) as a float, or `CaptureError` at `loc`: not a number (bools and
    strings are not), not finite, or beyond float32's range (an integer of 400 digits, 1e40)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CaptureError(f"{loc}: expected {what}, got {shown(value)}")
    try:
        f = float(value)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise CaptureError(f"{loc}: expected {what}, got {shown(value)}")
    if abs(f) > FLOAT32_MAX:
        raise CaptureError(f"{loc}: {shown(value)} is beyond float32's range (|x| <= 3.4e38)")
    return f


def number_field(d: Mapping[str, Any], key: str, where: str, default: float | None) -> float:
    """``d[key]`` as a finite float (`as_float`), or ``default`` when absent (None: required)."""
    if key not in d:
        if default is None:
            raise CaptureError(f"{where}: missing key '{key}'")
        return float(default)
    return as_float(d[key], field_loc(where, key))


def triple_field(d: Mapping[str, Any], key: str, where: str, default=None) -> np.ndarray:
    """``d[key]`` as 3 finite float64 numbers, or ``default`` when absent (None: required)."""
    if key not in d:
        if default is None:
            raise CaptureError(f"{where}: missing key '{key}'")
        return np.asarray(default, dtype=np.float64)
    value = d[key]
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or len(value) != 3 or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
        raise CaptureError(f"{field_loc(where, key)}: expected 3 numbers, got {shown(value)}")
    if any(isinstance(v, float) and not math.isfinite(v) for v in value):
        raise CaptureError(f"{field_loc(where, key)}: values must be finite, got {shown(value)}")
    return np.array([as_float(v, field_loc(where, key), "finite numbers") for v in value], np.float64)


def check_keys(obj: Mapping, allowed, where: str, what: str) -> None:
    """`CaptureError` for the first key of ``obj`` not in ``allowed``, naming ``what`` it is in."""
    for key in obj:
        if key not in allowed:
            raise CaptureError(f"{where}: unknown key {key!r} in {what} (allowed: {', '.join(allowed)})")


def object_field(value: Any, where: str) -> Mapping:
    """``value`` if it is a JSON object, else `CaptureError`."""
    if not isinstance(value, Mapping):
        raise CaptureError(f"{where}: expected an object, got {type(value).__name__}")
    return value


def without_nulls(value):
    """`value` with every object key whose value is null removed, at any depth (``extras`` left as
    written): null means absent, so an optional key falls back to its default and a required one
    is reported missing."""
    if isinstance(value, dict):
        return {k: (v if k == "extras" else without_nulls(v)) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [without_nulls(v) for v in value]
    return value


def positive_field(d: Mapping, key: str, where: str) -> Optional[float]:
    """``d[key]`` as a number > 0, or None when absent."""
    if key not in d:
        return None
    value = number_field(d, key, where, None)
    if value <= 0:
        raise CaptureError(f"{field_loc(where, key)}: must be > 0, got {value!r}")
    return value


def string_field(d: Mapping, key: str, where: str) -> str:
    """``d[key]`` as a non-empty string."""
    value = d[key]
    if not isinstance(value, str) or not value:
        raise CaptureError(f"{field_loc(where, key)}: expected a non-empty string, got {value!r}")
    return value
