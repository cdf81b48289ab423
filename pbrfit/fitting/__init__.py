"""Fitting maps to a capture: the options (`options`), the observations (`observations`), the
objective and its normal matrix (`objective`, `normal_matrix`, `parameters`, `noise`), the solvers
(`solvers/`), the passes over map levels (`passes`, `runner`, `resolution`, `initialisation`,
`sharding`), the stages after the solve (`stages/`), the result and its uncertainty (`result`,
`uncertainty`) and `fit` itself (`api`). Named `fitting` so that `pbrfit.fit` is the function.

May import: `pbrfit.physics`, `pbrfit.io`, `pbrfit.lighting`, `pbrfit.render`; `pbrfit.scene`
only at its entry (loading a capture).
"""

from . import (
    api,
    initialisation,
    noise,
    normal_matrix,
    objective,
    observations,
    options,
    parameters,
    passes,
    resolution,
    result,
    runner,
    sharding,
    solvers,
    stages,
    uncertainty,
)
