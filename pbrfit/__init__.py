"""pbrfit: differentiable glTF PBR material fitting in JAX.

The rooms are subpackages, each importing only the ones below it: `physics` (the BRDF, colour,
lights, textures, the material), `io` (files), `lighting` (environment light), `scene` (the
capture and its fixed geometry), `render`, `fitting` (the options, solvers and stages), `checks`
(gradient checks) and `cli` (the command). This module only re-exports the public API, each
name imported on first use, so `import pbrfit` loads no JAX (nor does importing a room: see
`pbrfit.lazy`).
"""

import importlib
import os
from importlib import metadata


def _xla_workarounds() -> None:
    """jaxlib 0.10.2 on the CPU miscompiles a fused reduce-then-broadcast (``sum(a * b, -1,
    keepdims=True) * b``) once an array passes 2**15 elements (jax-ml/jax#39103): jitted results
    silently differ from eager ones. Turning that YNN fusion off is the upstream workaround. The
    flag only exists in that release, and XLA rejects unknown flags, so it is set for it alone
    (before the backend starts, which reads XLA_FLAGS once)."""
    try:
        version = metadata.version("jaxlib")
    except metadata.PackageNotFoundError:
        return
    flag = "--xla_cpu_experimental_ynn_fusion_type=-reduce"
    if version == "0.10.2" and flag not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()


_xla_workarounds()

from .errors import CaptureError  # noqa: E402
from .lazy import submodules_on_access  # noqa: E402

__version__ = "0.1.0"

# name -> (module, attribute); resolved on first access so `import pbrfit` stays light.
_LAZY = {
    "brdf": ("physics", "brdf"),
    "color": ("physics", "color"),
    "Material": ("physics.material", "Material"),
    "Model": ("physics.model", "Model"),
    "load_capture": ("scene.capture", "load_capture"),
    "Capture": ("scene.capture", "Capture"),
    "Camera": ("scene.camera", "Camera"),
    "GBuffer": ("scene.gbuffer", "GBuffer"),
    "compute_gbuffer": ("scene.gbuffer", "compute_gbuffer"),
    "render_capture": ("render.views", "render_capture"),
    "fit": ("fitting.api", "fit"),
    "FitOptions": ("fitting.options", "FitOptions"),
    "StructuredLM": ("fitting.solvers.structured", "StructuredLM"),
    "FitResult": ("fitting.result", "FitResult"),
    "PixelIBLSettings": ("lighting.settings", "PixelIBLSettings"),
    "read_material": ("io.material_files", "read_material"),
    "write_material": ("io.material_files", "write_material"),
}

__all__ = ["CaptureError", *_LAZY]
# the rooms (subpackages), on first access
_rooms = submodules_on_access(__name__, __path__)


def __getattr__(name):
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(importlib.import_module(f".{module}", __name__), attr)
    return _rooms(name)
