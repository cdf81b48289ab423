"""pbrfit: differentiable glTF PBR material fitting in JAX.

The physics modules (`brdf`, `color`, `lights`, `textures`, `material`, `render`) import only
JAX; capture loading, ray casting and fitting are imported on first use.
"""

import importlib

from . import brdf, color
from .errors import CaptureError
from .material import Material
from .model import Model

__version__ = "0.1.0"

# name -> (module, attribute); resolved on first access so `import pbrfit` stays light.
_LAZY = {
    "load_capture": ("scene", "load_capture"),
    "Capture": ("scene", "Capture"),
    "Camera": ("gbuffer", "Camera"),
    "GBuffer": ("gbuffer", "GBuffer"),
    "compute_gbuffer": ("gbuffer", "compute_gbuffer"),
    "render_capture": ("views", "render_capture"),
    "fit": ("fit", "fit"),
    "FitResult": ("fit", "FitResult"),
    "read_material": ("io", "read_material"),
    "write_material": ("io", "write_material"),
}

__all__ = ["brdf", "color", "CaptureError", "Material", "Model", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(importlib.import_module(f".{module}", __name__), attr)
    if name in ("lights", "textures", "render", "ibl", "environment", "montecarlo", "scene", "gbuffer",
                "io", "views", "fit", "outputs", "model"):
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'pbrfit' has no attribute {name!r}")
