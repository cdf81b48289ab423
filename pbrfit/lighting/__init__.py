"""How environment light reaches a point: the environment map (`environment`), the split
sum's tables and LUT (`brdf_lut`, `ibl`), per-pixel lobe integrals (`lobe_integrals`,
`pixel_ibl`) and the Monte Carlo reference integrator (`sampling`, `montecarlo`) the others are
measured against; the mesh's occlusion of the environment reaches all three as a `visibility`
table (cast by `pbrfit.scene.occlusion`). The knobs a fit is given, free of JAX, are in
`settings`.

May import: `pbrfit.physics`, `pbrfit.io`.
"""

from ..lazy import submodules_on_access

# its modules, imported on first access (`pbrfit.lazy`): importing the room loads none of them
__getattr__ = submodules_on_access(__name__, __path__)
