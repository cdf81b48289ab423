"""pbrfit: differentiable glTF PBR material fitting in JAX."""

from . import brdf
from .errors import CaptureError
from .model import Model

__version__ = "0.1.0"
