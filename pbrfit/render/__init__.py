"""Rendering: shading a view's pixels under a `Model`, lights and environment light (`shade`),
every view of a capture (`views`) and writing renders as a capture folder (`output`).

May import: `pbrfit.physics`, `pbrfit.io`, `pbrfit.lighting`, `pbrfit.scene`.
"""

from ..lazy import submodules_on_access

# its modules, imported on first access (`pbrfit.lazy`): importing the room loads none of them
__getattr__ = submodules_on_access(__name__, __path__)
