"""Files: images through OpenImageIO (`images`), atomic writes and output folders (`atomic`),
JSON fields named in errors (`json_fields`), lights as `capture.json` holds them (`lights`),
material folders (`material_files`), glTF export (`gltf_export`) and a fit's output folder
(`outputs`).

May import: `pbrfit.physics` (types, colour encoding), `pbrfit.errors`, `pbrfit.transfer`.
"""

from ..lazy import submodules_on_access

# its modules, imported on first access (`pbrfit.lazy`): importing the room loads none of them
__getattr__ = submodules_on_access(__name__, __path__)
