"""The fit's defaults and the choices its options take: plain names and numbers, no JAX, so
that the command line's parser, which shows them in ``pbrfit fit --help``, loads none. The
modules that use them import them from here (and re-export them where they were first named)."""

__all__ = ["MATERIAL_MAPS", "IBL_MODES", "LOSSES", "LOSS_SCALE", "NOISE_LEVELS", "MAX_PIXEL_SAMPLES",
           "DEFAULT_SOLVER", "OPTX_SOLVERS", "SOLVERS", "RTOL", "ATOL", "NOISE_RTOL", "CG_RTOL", "COARSE_STEPS",
           "MAX_STEPS", "CONTINUATION", "QUALITY", "STRUCTURED_ONLY"]

#: The material maps a fit can fit or hold (``fit=``, ``fixed=``); "normal" can only be fitted.
MATERIAL_MAPS = ("base_color", "metallic", "roughness")
#: What `fit` may integrate a capture's environment light with (``ibl=``); the first is the default
#: ("auto": the split sum, and per-pixel integrals where its fit's residuals show light it cannot
#: model, `pbrfit.fitting.stages.ibl`).
IBL_MODES = ("auto", "split_sum", "per_pixel")
#: Robust losses, as residual transforms r -> r sqrt(ρ(r²)/r²) (so the objective stays a sum of
#: squares; `pbrfit.fitting.objective.robust_residual`).
LOSSES = ("l2", "huber", "cauchy")
#: Default scale of the robust losses, in image units (a few times a typical noise level).
LOSS_SCALE = 0.05
#: How `fit` treats the images' noise: "uniform" (plain least squares) or "estimated" (a second
#: fit weighted by the first fit's noise level function, `pbrfit.fitting.noise`).
NOISE_LEVELS = ("uniform", "estimated")
#: Largest n of n × n samples per pixel (`pbrfit.fitting.observations.observations_from_capture`):
#: memory and time grow as n².
MAX_PIXEL_SAMPLES = 4

#: The solver a fit runs unless asked for another: `pbrfit.fitting.solvers.structured.StructuredLM`.
DEFAULT_SOLVER = "structured"
#: The optimistix solvers a fit can run by name (`pbrfit.fitting.solvers.optx.make_solver`).
OPTX_SOLVERS = ("lm", "gn", "dogleg", "bfgs", "lbfgs", "ncg", "adam")
#: Every solver a fit can run by name: the structured one (the default), then the optimistix ones.
SOLVERS = (DEFAULT_SOLVER,) + OPTX_SOLVERS

#: Relative stopping tolerance: an accepted step that lowers E by less than ``RTOL · E``, or any
#: step whose predicted and actual changes of E are both within it, ends the solve (also the
#: named optimistix solvers' rtol).
RTOL = 1e-6
#: Absolute stopping tolerance: a step that moves no value by more than this ends the solve (also
#: the named optimistix solvers' atol).
ATOL = 1e-5
#: Noise-relative stopping tolerance (the structured solver's): an accepted step whose actual and
#: predicted decreases of E are both within ``NOISE_RTOL · E · p / (n - p)`` ends the solve (p free
#: channels, n pixel residuals). E / (n - p) is σ̂² / 2, the residuals' variance the fit reports,
#: so the test reads "the step's decrease is under NOISE_RTOL · p σ̂² / 2": what a quadratic's last
#: step gains when its parameters are within √NOISE_RTOL of their standard errors (RMS over the
#: channels), 0.1 σ here; steps past it move the maps by less than their noise. On noiseless
#: images of an exact model E falls by orders of magnitude a step down to its float32 floor, so
#: the test ends no such solve early. 0: off (``quality="best"``).
NOISE_RTOL = 0.01
#: Relative residual at which a step's conjugate gradients stop, ||r|| <= CG_RTOL ||g|| (an inexact
#: Levenberg-Marquardt step; `fit --cg-rtol` trades it for speed, measured in docs/results.md).
CG_RTOL = 1e-3

#: Default step limits: per coarse level, and for the final level.
COARSE_STEPS = 20
MAX_STEPS = 40
#: The continuation's weights of a smoothness prior over the final level's first steps, relative
#: to the data's mean curvature per texel at the start (`pbrfit.fitting.passes` says how they are
#: used; `experiments/solvers.md` has the numbers that chose them).
CONTINUATION = (0.0035, 0.00035)

#: The options only the structured solver reads (a rung of `QUALITY` leaves them to another).
STRUCTURED_ONLY = ("cg_rtol", "noise_rtol", "continuation")
#: The speed ladder (``quality=``, ``--quality``): per rung, the options it sets where they are
#: left at their defaults. "draft" previews in a fraction of the default's time (no search,
#: repair, uniform check or continuation; each step's conjugate gradients to 0.1; stops at a step
#: that lowers the loss by less than 0.1% of it, or after half the default's steps; pixel centres,
#: not the automatic footprint's two fits); "best" runs
#: the solve to tighter tolerances (no noise-relative stop) and a larger step budget.
#: `experiments/speed.md` measures each.
QUALITY = {
    "draft": dict(search=False, repair=False, uniform_check=False, continuation=None, cg_rtol=0.1, rtol=1e-3,
                  max_steps=MAX_STEPS // 2, pixel_samples=1),
    "default": {},
    "best": dict(cg_rtol=1e-4, rtol=1e-8, noise_rtol=0.0, max_steps=4 * MAX_STEPS),
}

