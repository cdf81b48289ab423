"""The stages after a solve, behind one protocol and run as a list (`pipeline`): the repair of
texels that fit worse than the noise explains or are out of line with their neighbours
(`repair`), the uniform check (`selection`) and the hold of unconstrained roughness
(`unconstrained`); the pixel footprint's choice (`footprint`), made within the last level; and
the environment light's model (`ibl`), chosen between whole fits.

May import: the rest of `pbrfit.fitting` but `api`.

Its modules are imported on first access (`pbrfit.lazy`), not here: the passes and the result
import single stages, and a stage imports the result.
"""

from ...lazy import submodules_on_access

__getattr__ = submodules_on_access(__name__, __path__)
