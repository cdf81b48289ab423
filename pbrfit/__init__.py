"""pbrfit: differentiable glTF PBR material fitting in JAX.

The physics modules (`brdf`, `color`, `lights`, `textures`, `material`, `render`) import only
JAX; capture loading, ray casting and fitting are imported on first use.
"""

import importlib
import os
import pkgutil


def _xla_workarounds() -> None:
    """jaxlib 0.10.2 on the CPU miscompiles a fused reduce-then-broadcast (``sum(a * b, -1,
    keepdims=True) * b``) once an array passes 2**15 elements (jax-ml/jax#39103): jitted results
    silently differ from eager ones. Turning that YNN fusion off is the upstream workaround. The
    flag only exists in that release, and XLA rejects unknown flags, so it is set for it alone
    (before the backend starts, which reads XLA_FLAGS once)."""
    from importlib import metadata

    try:
        version = metadata.version("jaxlib")
    except metadata.PackageNotFoundError:
        return
    flag = "--xla_cpu_experimental_ynn_fusion_type=-reduce"
    if version == "0.10.2" and flag not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()


_xla_workarounds()

from . import brdf, color  # noqa: E402
from .errors import CaptureError  # noqa: E402
from .material import Material  # noqa: E402
from .model import Model  # noqa: E402

__version__ = "0.1.0"

# name -> (module, attribute); resolved on first access so `import pbrfit` stays light.
_LAZY = {
    "load_capture": ("scene", "load_capture"),
    "Capture": ("scene", "Capture"),
    "Camera": ("camera", "Camera"),
    "GBuffer": ("gbuffer", "GBuffer"),
    "compute_gbuffer": ("gbuffer", "compute_gbuffer"),
    "render_capture": ("views", "render_capture"),
    "FitResult": ("fit", "FitResult"),
    "PixelIBLSettings": ("pixel_ibl", "PixelIBLSettings"),
    "read_material": ("material_files", "read_material"),
    "write_material": ("material_files", "write_material"),
}

__all__ = ["brdf", "color", "CaptureError", "Material", "Model", "fit", *_LAZY]
_SUBMODULES = frozenset(m.name for m in pkgutil.iter_modules(__path__))


def __getattr__(name):
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(importlib.import_module(f".{module}", __name__), attr)
    # submodules, on first access; `pbrfit.fit` is the fit module, and calling it calls `pbrfit.fit.fit`
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'pbrfit' has no attribute {name!r}")
