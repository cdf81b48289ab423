"""The stages after the solve, behind one protocol, run as a list.

Each stage (`Stage`) says whether the options turn it off (`Stage.turned_off`), why it does not
apply to this fit (`Stage.skipped`, None where it does), and runs (`Stage.run`): it reads and
changes a `StageState` (the texel values, the linearisation at them, the problem) and returns
its findings, the report's entry under the stage's name. `run_stages` runs them in order and
gives, besides each entry, one uniform summary per stage for the report's "stages": its name,
whether it ran or why not, its wall time (its solver steps included) and its solver steps.

The stages, in their order: the repair of texels left in a wrong basin (`repair`), the uniform
check of metallic and roughness (`selection`), the hold of roughness the images do not
constrain (`unconstrained`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Optional, Protocol, Sequence

import numpy as np

from ..objective import Problem
from ..runner import announce, timed_rest
from .repair import repair_skipped, run_repair
from .selection import run_uniform_check, uniform_check_skipped
from .unconstrained import hold_skipped, run_hold

__all__ = ["Stage", "StageState", "Repair", "UniformCheck", "UnconstrainedHold", "STAGES", "run_stages",
           "TURNED_OFF"]

#: A stage's report entry when the options turn it off.
TURNED_OFF = "turned off"


@dataclasses.dataclass
class StageState:
    """What the stages after the solve share: the fit's options, the solver runner and its
    compiler, the problem of the final level and its texel values ``xs`` (T, K) with the
    linearisation at them (residuals, Jacobians), the final map shape, the texels seen, the
    channels fitted (K,), the free parameters, the pixels, the progress callback's ``where``,
    the channels the uniform check made one value ({channel: value}), the standard errors
    at ``xs`` where the last stage computed them for the result (σ, σ̂²), else None, and the
    problem the fit's search ran on (its pixel centres where the final level has samples), for
    the repair's searches."""

    options: Any
    runner: Any
    compiler: Any
    problem: Problem
    xs: np.ndarray
    linearization: tuple
    final: tuple[int, int]
    seen: np.ndarray
    channels: np.ndarray
    num_free: int
    num_pixels: int
    where: dict
    uniform: dict = dataclasses.field(default_factory=dict)
    errors: Optional[tuple] = None
    search_on: Optional[Problem] = None


class Stage(Protocol):
    """A step after the solve."""

    name: str  # its report entry

    def turned_off(self, options) -> bool:
        """Whether the options turn it off."""

    def skipped(self, state: StageState) -> Optional[str]:
        """Why it does not apply to this fit, or None where it does."""

    def run(self, state: StageState) -> dict:
        """Run it on `state` (changed in place) and return its findings; their "steps" (or,
        for a stage of several parts, their parts' "steps") count its solver steps."""


class Repair:
    """Texels whose pixels fit worse than the noise explains, or out of line with their
    neighbours, started again from their neighbours (`pbrfit.fitting.stages.repair`)."""

    name = "repair"

    def turned_off(self, options) -> bool:
        return not options.repair

    def skipped(self, state: StageState) -> Optional[str]:
        return repair_skipped(state.options.solver, state.final, state.channels)

    def run(self, state: StageState) -> dict:
        state.xs, state.linearization, found = run_repair(
            state.runner, state.compiler, state.problem, state.xs, state.linearization, state.final, state.seen,
            state.channels, state.num_free, state.where, state.search_on)
        return found


class UniformCheck:
    """Metallic, then roughness, as one value where the images support no map
    (`pbrfit.fitting.stages.selection`)."""

    name = "uniform_check"

    def turned_off(self, options) -> bool:
        return not options.uniform_check

    def skipped(self, state: StageState) -> Optional[str]:
        o = state.options
        return uniform_check_skipped(o.solver, o.loss, o.smooth, state.final, state.channels)

    def run(self, state: StageState) -> dict:
        state.xs, state.linearization, state.problem, found, state.uniform = run_uniform_check(
            state.runner, state.problem, state.xs, state.linearization, state.channels, state.seen,
            state.num_pixels, state.where)
        return found


class UnconstrainedHold:
    """Roughness the images do not constrain held at the prior, base colour re-fitted
    (`pbrfit.fitting.stages.unconstrained`)."""

    name = "unconstrained"

    def turned_off(self, options) -> bool:
        return not math.isfinite(options.unconstrained_sigma)

    def skipped(self, state: StageState) -> Optional[str]:
        o = state.options
        return hold_skipped(o.solver, o.smooth, state.final, state.channels, state.uniform)

    def run(self, state: StageState) -> dict:
        o = state.options
        state.xs, state.linearization, state.problem, found, state.errors = run_hold(
            state.runner, state.problem, state.xs, state.linearization, state.channels, state.seen, state.final,
            state.num_pixels, o.unconstrained_sigma, int(o.uncertainty_radius), state.uniform)
        return found


#: The stages after the solve, in the order they run.
STAGES: tuple[Stage, ...] = (Repair(), UniformCheck(), UnconstrainedHold())


def stage_steps(found: dict) -> int:
    """The solver steps a stage's findings count: their own "steps", or their parts'."""
    if isinstance(found.get("steps"), int):
        return found["steps"]
    parts = found.get("passes", found.values())
    return sum(p.get("steps", 0) for p in parts if isinstance(p, dict))


def run_stages(stages: Sequence[Stage], state: StageState, clock: dict) -> tuple[dict, list]:
    """Run `stages` in order on `state`: ({name: findings or {"skipped": why}}, the uniform
    summaries [{name, ran, skipped, seconds, steps}]). A stage's own host-side time goes to
    ``clock[name]`` (`timed_rest`; its solver steps are counted as solve time)."""
    entries, summary = {}, []
    for stage in stages:
        t0 = time.perf_counter()
        why = TURNED_OFF if stage.turned_off(state.options) else stage.skipped(state)
        if why is not None:
            entries[stage.name] = dict(skipped=why)
        else:
            announce(state.options.progress, state.where, stage.name.replace("_", " "))
            with timed_rest(clock, stage.name):
                entries[stage.name] = stage.run(state)
        found = entries[stage.name]
        summary.append(dict(name=stage.name, ran=why is None, skipped=why, seconds=time.perf_counter() - t0,
                            steps=0 if why is not None else stage_steps(found)))
    return entries, summary
