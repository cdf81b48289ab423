"""The solvers a fit can be asked for by name (``--solver NAME``, ``solver="lm"``), each an
optimistix solver object: `solver_for` makes one, `solver_name` names one for the report.

``structured`` (the default) is pbrfit's `pbrfit.fitting.solvers.structured.StructuredLM`; the
others are the optimistix solvers of `pbrfit.fitting.solvers.optx` (``lm``, ``gn``, ``dogleg``,
``bfgs``, ``lbfgs``, ``ncg``, ``adam``). Every one starts from the same tolerances,
`pbrfit.fitting.defaults.RTOL` and `ATOL`; the names are `pbrfit.fitting.defaults.SOLVERS`.
"""

from __future__ import annotations

from typing import Optional

from ..defaults import ATOL, CG_RTOL, DEFAULT_SOLVER, NOISE_RTOL, OPTX_SOLVERS, RTOL, SOLVERS
from .optx import make_solver
from .structured import StructuredLM

__all__ = ["DEFAULT_SOLVER", "SOLVERS", "solver_for", "solver_name", "is_structured"]


def solver_for(name: str, rtol: Optional[float] = None, atol: Optional[float] = None,
               cg_rtol: Optional[float] = None, noise_rtol: Optional[float] = None):
    """The solver named `name` (one of `SOLVERS`), with the tolerances given (None: `RTOL`,
    `ATOL`, `CG_RTOL`, `NOISE_RTOL`; ``cg_rtol`` and ``noise_rtol`` are the structured solver's
    alone)."""
    rtol, atol = RTOL if rtol is None else float(rtol), ATOL if atol is None else float(atol)
    if name == DEFAULT_SOLVER:
        return StructuredLM(rtol, atol, CG_RTOL if cg_rtol is None else float(cg_rtol),
                            NOISE_RTOL if noise_rtol is None else float(noise_rtol))
    return make_solver(name, rtol, atol)


def solver_name(solver) -> str:
    """A solver's name for the report: its name in `SOLVERS` where `solver_for` makes one equal to
    it (with its tolerances), else its class's name."""
    if isinstance(solver, str):
        return solver
    if type(solver) is StructuredLM:
        return DEFAULT_SOLVER
    for name in OPTX_SOLVERS:
        try:  # (a solver holding arrays compares to an array)
            same = bool(solver_for(name, solver.rtol, solver.atol) == solver)
        except (AttributeError, TypeError, ValueError):
            same = False
        if same:
            return name
    return type(solver).__name__


def is_structured(solver) -> bool:
    """Whether `solver` (an object, or a name) is the structured solver, which the continuation,
    the repair, the uniform check and the hold of unconstrained texels need."""
    return solver == DEFAULT_SOLVER if isinstance(solver, str) else isinstance(solver, StructuredLM)
