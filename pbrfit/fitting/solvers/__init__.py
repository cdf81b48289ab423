"""The solvers that minimise the fit's objective, each an optimistix solver: the structured
projected Levenberg-Marquardt (`structured`, `StructuredLM`), the optimistix solvers run on the
same problem (`optx`), and the names a fit can ask for them by (`names`).

May import: the rest of `pbrfit.fitting` below the passes (objective, normal matrix, parameters).

Its modules are imported by `pbrfit.fitting` (through the runner), not here.
"""
