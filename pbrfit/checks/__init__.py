"""Gradient checks of the BRDF terms: finite differences (`finite_differences`), the terms
and their domains (`terms`) and the runs `pbrfit check-grads` makes (`gradcheck`).

May import: `pbrfit.physics`.
"""

from ..lazy import submodules_on_access

# its modules, imported on first access (`pbrfit.lazy`): importing the room loads none of them
__getattr__ = submodules_on_access(__name__, __path__)
