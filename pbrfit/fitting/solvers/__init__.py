"""The solvers that minimise the fit's objective, each an optimistix solver: the structured
projected Levenberg-Marquardt (`structured`, `StructuredLM`), the optimistix solvers run on the
same problem (`optx`), and the names a fit can ask for them by (`names`).

May import: the rest of `pbrfit.fitting` below the passes (objective, normal matrix, parameters).

Its modules are imported on first access (`pbrfit.lazy`), not here.
"""

from ...lazy import submodules_on_access

__getattr__ = submodules_on_access(__name__, __path__)
