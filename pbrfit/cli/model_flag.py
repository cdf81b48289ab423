"""``--model key=value,...``: the BRDF variant a command shades with (`pbrfit.Model`'s fields),
for `pbrfit fit` and `pbrfit render`, so that a capture made by a renderer with Burley diffuse
or a separable masking term is fitted and rendered with the matching model. The fields not given
stay as the capture requires (`pbrfit.render.views.model_for_capture`)."""

from __future__ import annotations

import dataclasses

from ..errors import CaptureError
from ..physics.model import DIFFUSES, DISTRIBUTIONS, FRESNELS, GEOMETRIES, IBLS, Model

__all__ = ["add_model_argument", "model_changes"]

_TRUE, _FALSE = ("true", "on", "yes", "1"), ("false", "off", "no", "0")


def add_model_argument(parser) -> None:
    parser.add_argument(
        "--model", metavar="KEY=VALUE[,...]",
        help="the BRDF variant (pbrfit.Model's fields): "
             f"distribution={'|'.join(DISTRIBUTIONS)}, geometry={'|'.join(GEOMETRIES)}, "
             f"fresnel={'|'.join(FRESNELS)}, diffuse={'|'.join(DIFFUSES)}, specular, metallic and "
             f"multiscatter=true|false, ibl={'|'.join('none' if i is None else i for i in IBLS)}, ior=NUMBER; "
             "default: the glTF BRDF, with the environment light and metal lobe the capture needs")


def model_changes(text) -> dict:
    """The `Model` fields ``--model`` sets, typed and checked (`CaptureError` naming the flag);
    {} where it is not given."""
    if text is None:
        return {}
    fields = {f.name: f for f in dataclasses.fields(Model)}
    changes = {}
    for item in text.split(","):
        key, sep, value = (part.strip() for part in item.partition("="))
        if not sep or not key:
            raise CaptureError(f"--model: expected KEY=VALUE pairs separated by commas, got {item.strip()!r}")
        if key not in fields:
            raise CaptureError(f"--model: unknown field {key!r}; expected one of {', '.join(fields)}")
        if key in changes:
            raise CaptureError(f"--model: {key} is given twice")
        default = fields[key].default
        if isinstance(default, bool):
            if value.lower() not in _TRUE + _FALSE:
                raise CaptureError(f"--model: {key} must be true or false, got {value!r}")
            changes[key] = value.lower() in _TRUE
        elif isinstance(default, float):
            try:
                changes[key] = float(value)
            except ValueError:
                raise CaptureError(f"--model: {key} must be a number, got {value!r}") from None
        else:
            changes[key] = None if key == "ibl" and value.lower() == "none" else value
    try:
        Model(**changes)
    except ValueError as err:
        raise CaptureError(f"--model: {err}") from None
    return changes
