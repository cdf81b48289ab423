"""Roughness the images do not constrain, held at the prior instead of fitted to the noise.

Where no highlight reaches a texel, its pixels hardly depend on its roughness: the objective is
nearly flat along it, and the least-squares value is set by the noise. It lands anywhere in
[`pbrfit.physics.brdf.MIN_ROUGHNESS`, 1], often on a bound, where its error is largest, while its
standard error says the images do not pin it down. On the peer layout with the cameras at
35° / 55° and the lights at 75° (`experiments/noise_floor.md`), a corner of 50 texels that no
highlight reaches took roughness values from 0.04 to 1.0 under a truth of about 0.45, with σ of
0.1 to 0.37: 1% of the texels carried 87% of the squared error.

So, as for texels no view sees, a parameter the images do not constrain is not fitted: after the
solve (and the repair and the uniform check), a texel whose roughness standard error, as
uncertainty.exr reports it, exceeds ``unconstrained_sigma`` (`UNCONSTRAINED_SIGMA`, a tenth of
the range: the images place it no better than ±0.2 at 2σ) has its roughness held at `PRIOR`'s
0.5, the middle of the range (no truth lies further than 0.5 from it, where a fitted value on a
bound can be a whole range off), and `HOLD_STEPS` solver steps re-fit those texels' base colour,
every other value kept. Where the images do pin the roughness down at 0.5 (its σ there is
within the threshold: the solve moved it off on evidence, a highlight's flank) the texel keeps
its fitted values (`HOLD_ROUNDS`). A held texel's σ in uncertainty.exr is what the images give
at 0.5, not the 0 of a channel the caller held.

Base colour and metallic are not held, and metallic is not re-fitted: the pixels' diffuse light
constrains base colour still, metallic's prior of 0 is no midpoint (holding both at the prior
made the flash scene's worse: the red channel 0.005 to 0.020, metallic 0.015 to 0.037), and re-fitting metallic under
the held roughness let it make up for it (the demo's all-texel metallic 0.137 to 0.174); so did
re-fitting the neighbours (peer scene roughness 0.049 against 0.045).

Measured (`experiments/noise_floor.md`, roughness RMSE with every value kept and with the hold):
noise of 1% of each pixel's value, peer scene 0.019 and 0.019, flash scene 0.039 and 0.022, the
35° / 55° layout 0.036 and 0.019; noise of std 0.01, peer scene 0.055 and 0.045, flash scene
0.059 and 0.037 (with metallic re-fitted too); the demo 0.115 and 0.059 (its base colour 0.050 and 0.054).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import numpy as np

from ..result import texel_standard_errors
from ..uncertainty import WindowCache
from ..objective import Problem, linearize
from ..parameters import FIT_GROUPS, PRIOR
from ..runner import problem_energy
from ..solvers.names import DEFAULT_SOLVER, is_structured
from ...transfer import to_device

__all__ = ["UNCONSTRAINED_SIGMA", "HOLD_STEPS", "HOLD_ROUNDS", "ROUGHNESS", "hold_skipped", "unconstrained_texels", "run_hold"]

#: A texel's roughness is held at the prior where its standard error exceeds this (perceptual
#: roughness units; the range is [MIN_ROUGHNESS, 1]). `math.inf` holds none.
UNCONSTRAINED_SIGMA = 0.1
#: Solver steps re-fitting the held texels' base colour once the roughness is held (the uniform check's
#: re-fit, `pbrfit.fitting.stages.selection.REFIT_STEPS`, takes as many).
HOLD_STEPS = 10
#: Rounds of the hold: the texels whose σ exceeds the threshold at their fitted values, then,
#: once held, those of them whose σ exceeds it at the prior too (the others go back to their
#: fitted values, and the rest are re-fitted again).
HOLD_ROUNDS = 2
#: The roughness channel of the texel values, and the base colour's.
(ROUGHNESS,) = FIT_GROUPS["roughness"]
BASE_COLOR = list(FIT_GROUPS["base_color"])


def hold_skipped(solver, smooth, final, channels, uniform) -> Optional[str]:
    """Why roughness is not held anywhere in a fit, or None where the test applies."""
    if tuple(final) == (1, 1):
        return "a uniform material"
    if not is_structured(solver):
        return f"needs the {DEFAULT_SOLVER} solver"
    if smooth > 0:
        return "the smoothness prior already ties the texels together"
    if not channels[ROUGHNESS] > 0:
        return "roughness is not fitted"
    if ROUGHNESS in uniform:
        return "roughness is one value (uniform check)"
    return None


def unconstrained_texels(sigma, seen, threshold: float):
    """(T,) bool: seen texels whose roughness standard error exceeds `threshold`."""
    s = np.asarray(sigma)[:, ROUGHNESS]
    return np.asarray(seen, bool) & np.isfinite(s) & (s > threshold)


def run_hold(runner, problem: Problem, xs, linearization, channels, seen, final, num_pixels: int, threshold: float,
             uncertainty_radius: int, uniform=()):
    """Hold at `PRIOR` the roughness of the texels the images do not constrain, and re-fit their
    base colour.
    ``uniform``: the channels the uniform check made one common value (not per texel).

    Returns (x, linearisation, problem, report, errors): the problem with those texels'
    roughness no longer free (the re-fit frees their base colour alone), the report's
    "unconstrained" entry (the threshold, the texels held, those the images constrain at the
    prior and so left as fitted, the steps, the objective before and after), and the standard
    errors at the x returned (σ (T, K), σ̂²: `pbrfit.fitting.result.texel_standard_errors`, which
    the result then reads instead of computing them again: they depend on which channels are
    fitted, not on which the final problem frees), or None where x is not where they were taken.
    """
    t = int(np.prod(final))
    r, jac = linearization
    xs = np.asarray(xs, np.float32)
    energy = problem_energy(r, xs, problem)
    texel_channels = np.asarray(channels, np.float32).copy()
    texel_channels[list(uniform)] = 0.0
    windows = WindowCache()  # a re-fit moves a few texels: the other windows are kept

    def unconstrained(x, jac, energy, problem):
        errors = texel_standard_errors(problem, x[:t], jac, energy, final, texel_channels, seen[:t], num_pixels,
                                       len(uniform), uncertainty_radius, windows)
        out = np.zeros(len(x), bool)
        out[:t] = unconstrained_texels(errors[0], seen[:t], threshold)
        return out, errors

    held, errors = unconstrained(xs, jac, energy, problem)
    report = dict(threshold=float(threshold), texels=int(held.sum()), constrained_at_prior=0, steps=0)
    x_held, steps = xs, 0
    for attempt in range(HOLD_ROUNDS):  # the texels held, then those the images leave free at the prior too
        if not held.any():
            report["texels"] = 0
            return xs, linearization, problem, report, errors if attempt == 0 else None
        free = np.array(problem.free, np.float32)
        free[held, ROUGHNESS] = 0.0
        kept = dataclasses.replace(problem, free=jax.device_put(free, problem.free.sharding))  # what finish reads
        refit = np.zeros_like(free)  # the held texels' base colour alone (see the module docstring)
        refit[np.ix_(held, BASE_COLOR)] = free[np.ix_(held, BASE_COLOR)]
        x_held = xs.copy()
        x_held[held, ROUGHNESS] = PRIOR[ROUGHNESS]
        if refit.any():
            x_held, info = runner.refit(to_device(x_held, np.float32),
                                        dataclasses.replace(problem, free=jax.device_put(refit, problem.free.sharding)),
                                        held, HOLD_STEPS, int(np.sum(refit)), linearization)
            x_held, steps = np.asarray(x_held, np.float32), steps + int(info["steps"])
            r_held, jac_held = runner.linearization
        else:  # base colour held by the caller: nothing to re-fit
            r_held, jac_held, _ = jax.jit(linearize)(to_device(x_held, np.float32), kept)
        e_held = problem_energy(r_held, x_held, kept)
        # with roughness free again at 0.5: where the images pin it down there, the solve moved it
        # away on evidence (a highlight's flank), and its value stays
        still, errors = unconstrained(x_held, jac_held, e_held, problem)
        still &= held
        if still.sum() == held.sum() or attempt == HOLD_ROUNDS - 1:
            break
        report["constrained_at_prior"] += int(held.sum() - still.sum())
        held = still
    report.update(texels=int(held.sum()), steps=steps, energy_before=float(energy), energy_after=float(e_held))
    linearization = (r_held, jac_held)
    return x_held, linearization, kept, report, errors

