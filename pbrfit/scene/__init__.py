"""The fixed geometry and what is known of it: the capture (`capture`: `capture.json` read and
checked, its frames and their cameras, every error named), cameras, meshes and glTF reading,
uv layout, ray casting, the per-view G-buffers computed once and the environment's visibility
from the mesh's points (`occlusion`).

May import: `pbrfit.physics`, `pbrfit.io`, `pbrfit.lighting`.
"""

from . import (
    camera,
    capture,
    gbuffer,
    gltf_accessors,
    gltf_geometry,
    gltf_read,
    mesh,
    occlusion,
    raycast,
    uv_layout,
)
