"""Gradient checks of the BRDF terms: finite differences (`finite_differences`), the terms
and their domains (`terms`) and the runs `pbrfit check-grads` makes (`gradcheck`).

May import: `pbrfit.physics`.
"""

from . import finite_differences, gradcheck, terms
