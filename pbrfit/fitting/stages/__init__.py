"""The stages after a solve: the pixel footprint's choice (`footprint`), the repair of texels
that fit worse than the noise explains (`misfit`, `repair`), the uniform check (`selection`) and
the hold of unconstrained roughness (`unconstrained`).

May import: the rest of `pbrfit.fitting` but `api`.

Its modules are imported by `pbrfit.fitting`, not here: the passes and the result import single
stages, and a stage imports the result.
"""
