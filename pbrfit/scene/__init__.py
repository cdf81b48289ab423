"""The fixed geometry and what is known of it: the capture (`capture`: `capture.json` read and
checked, its frames and their cameras, every error named), cameras, meshes and glTF reading,
uv layout, ray casting, the per-view G-buffers computed once and the environment's visibility
from the mesh's points (`occlusion`).

May import: `pbrfit.physics`, `pbrfit.io`, `pbrfit.lighting`.
"""

from ..lazy import submodules_on_access

# its modules, imported on first access (`pbrfit.lazy`): importing the room loads none of them
__getattr__ = submodules_on_access(__name__, __path__)
