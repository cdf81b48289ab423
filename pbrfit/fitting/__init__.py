"""Fitting maps to a capture: the options (`options`), the observations (`observations`), the
objective and its normal matrix (`objective`, `normal_matrix`, `parameters`, `noise`), the solvers
(`solvers/`), the passes over map levels (`passes`, `runner`, `resolution`, `initialisation`,
`sharding`), the stages after the solve (`stages/`), the result and its uncertainty (`result`,
`uncertainty`) and `fit` itself (`api`); the defaults and choices of the options, free of JAX
(`defaults`). Named `fitting` so that `pbrfit.fit` is the function.

May import: `pbrfit.physics`, `pbrfit.io`, `pbrfit.lighting`, `pbrfit.render`; `pbrfit.scene`
only at its entry (loading a capture).
"""

from ..lazy import submodules_on_access

# its modules, imported on first access (`pbrfit.lazy`): importing the room loads none of them
__getattr__ = submodules_on_access(__name__, __path__)
