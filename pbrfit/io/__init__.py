"""Files: images through OpenImageIO (`images`), atomic writes and output folders (`atomic`),
JSON fields named in errors (`json_fields`), lights as `capture.json` holds them (`lights`),
material folders (`material_files`), glTF export (`gltf_export`) and a fit's output folder
(`outputs`).

May import: `pbrfit.physics` (types, colour encoding), `pbrfit.errors`, `pbrfit.transfer`.
"""

from . import atomic, gltf_export, images, json_fields, lights, material_files, outputs
