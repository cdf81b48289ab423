"""The physics of shading, in pure JAX: the `Model` (which BRDF variant, static under `jit`),
every BRDF term as a function of cosines and alpha with its named floors (`brdf`, `clamps`),
colour (sRGB, exposure, tone maps), punctual lights, texture sampling and the `Material` pytree.

May import: `pbrfit.errors`, `pbrfit.transfer`, JAX. Never I/O, never a room above it.
"""

from ..lazy import submodules_on_access

# its modules, imported on first access (`pbrfit.lazy`): importing the room loads none of them
__getattr__ = submodules_on_access(__name__, __path__)
