"""The solvers that minimise the fit's objective: the structured projected
Levenberg-Marquardt (`structured`) and the optimistix solvers run on the same problem (`optx`).

May import: the rest of `pbrfit.fitting` below the passes (objective, normal matrix, parameters).

Its modules are imported by `pbrfit.fitting` (through the runner), not here.
"""
