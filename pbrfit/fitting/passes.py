"""One pass of a fit: the solve at each level, then the repair, the uniform check and the hold of
roughness the images do not constrain (`pbrfit.fitting.stages.unconstrained`).

`fit_pass` runs the levels of a fit (`pbrfit.fitting.resolution.schedule`: the final map size, or
coarse to fine), each from the last one's maps: the grid start, the continuation (a smoothness prior
of falling weight over the first steps), the coordinate search of metallic and roughness, the
settling steps and the released ones; on the final level the pixel footprint's choice
(`pbrfit.fitting.stages.footprint`), then the repair (`pbrfit.fitting.stages.repair`) and the
uniform check (`pbrfit.fitting.stages.selection`), and the result (`pbrfit.fitting.result.finish`).
`pbrfit.fitting.api.fit_observations` runs one pass, or two with ``noise_level="estimated"``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Mapping, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .defaults import COARSE_STEPS, CONTINUATION, MAX_STEPS
from .result import FitResult, finish
from .stages.footprint import centres_explain_better, final_residuals, footprint_energies, samples_side
from .initialisation import coordinate_search, grid_initialise
from .observations import Observations, coverage_counts, layout_for, neighbour_pairs
from .parameters import FIT_GROUPS, channel_mask, prior
from .resolution import default_resolution, schedule
from .runner import Compiler, PendingTables, Runner, announce, jitted_normal_blocks, problem_key, search_inputs, timed
from .stages.pipeline import STAGES, StageState, run_stages
from .stages.selection import SELECTABLE
from .sharding import pixel_mesh, shard_problem
from .objective import Problem, texel_grid
from .stencil import with_stencil
from ..physics.textures import resample_map, sample_bilinear
from ..physics.model import Model
from ..transfer import to_device
from ..lighting.pixel_ibl import per_row

__all__ = ["fit_pass", "PassInputs", "continuation_scale", "with_smooth", "COARSE_STEPS", "MAX_STEPS", "SEARCH_AFTER",
           "SEARCH_ROUNDS", "CONTINUATION", "SETTLE_STEPS", "RELEASED_STEPS", "PROBE_STEPS"]

#: With ``search=True`` the final level runs this many steps, then `coordinate_search`
#: (`SEARCH_ROUNDS` sweeps of the four parity classes), then the rest of its steps
#: (experiments/solvers.md).
SEARCH_AFTER = 15
SEARCH_ROUNDS = 1
#: Continuation (graduated smoothing; A. Blake & A. Zisserman, "Visual Reconstruction", MIT
#: Press 1987, ch. 7): the final level's first `SEARCH_AFTER` steps are split evenly over the
#: weights `CONTINUATION` of a smoothness prior; after the search, `SETTLE_STEPS` more run under
#: the last weight (the search moves texels few pixels see into minima of those few pixels), and the
#: steps after them run on the objective as asked (no prior unless ``smooth`` is set). The prior
#: pulls texels that few pixels pin down, and patches that the grid start put in a wrong
#: roughness basin, towards their neighbours' basin; released, each texel settles in the minimum
#: of its own data there. Weights are relative to the data's mean curvature per texel at the
#: start (`continuation_scale`), so they do not depend on the images' brightness (exactly so for
#: linear images).
#: `experiments/solvers.md` has the numbers that chose them. The structured solver only (the
#: optimistix ones would compile once per phase), and only where at least `RELEASED_STEPS` steps
#: are left without the prior: with fewer (``max_steps`` under 25) there is no continuation, and
#: with fewer after the settling steps (under 30) no settling.
SETTLE_STEPS = 5
RELEASED_STEPS = 10
#: The automatic footprint's early stop: after the centres' last steps, the samples' first
#: `PROBE_STEPS` (the settling ones) run, and where their data term is not yet below the
#: centres' final one the centres are kept without the rest (structured solver; the model the
#: images need gets there at once, experiments/solvers.md).
PROBE_STEPS = SETTLE_STEPS


def _fixed_values(fixed: Mapping, shape: tuple[int, int], k: int = 5) -> np.ndarray:
    """(H, W, k) values of the channels held fixed (`prior` where nothing is given)."""
    out = np.broadcast_to(prior(k), shape + (k,)).copy()
    for name, value in (fixed or {}).items():
        if name not in FIT_GROUPS:
            raise ValueError(f"unknown fixed map {name!r}; expected some of {', '.join(FIT_GROUPS)}")
        chans = list(FIT_GROUPS[name])
        if max(chans) >= k:
            raise ValueError(f"a fixed {name!r} map is not supported: fit it or leave it out")
        v = np.asarray(value, np.float32)
        if v.ndim == 3:
            v = resample_map(v, shape)
        out[..., chans] = np.broadcast_to(v.reshape(v.shape[:-1] + (-1,)) if v.ndim == 3 else v, shape + (len(chans),))
    return out


def _upsample(x: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    uv = np.stack(np.meshgrid(u, v, indexing="xy"), -1)
    return np.asarray(sample_bilinear(jnp.asarray(x), jnp.asarray(uv), "clamp"))


@dataclasses.dataclass(frozen=True)
class PassInputs:
    """What a pass fits with besides its `FitOptions`: the shading (``model`` and its ``ibl``
    tables or integrals, those of the capture the observations come from), the same capture's
    observations at pixel centres when ``obs`` holds several samples per pixel (``centres``, and
    ``centre_ibl``, their integrals (or occlusion factors) where the IBL has rows (`per_row`); ``select_footprint``: keep the
    footprint that explains the pixels better, `pbrfit.fitting.stages.footprint`), the (T, K)
    texel values to ``start`` from at the final level (no grid start, no coarser levels) and the
    ``setup_time`` spent before the pass, for its report."""

    model: Model = Model()
    ibl: Any = None
    centres: Optional[Observations] = None
    centre_ibl: Any = None
    select_footprint: bool = False
    start: Optional[np.ndarray] = None
    setup_time: float = 0.0


def fit_pass(obs: Observations, options, inputs: PassInputs,
             shared: Optional[dict] = None) -> tuple[FitResult, np.ndarray]:
    """One fit (`pbrfit.fitting.api.fit_observations`) with ``options`` (a
    `pbrfit.fitting.options.FitOptions`, which imports this module's defaults): the result and
    the final (T, K) texel values. ``shared``: a dict that keeps the solver runner, its compiler (whose clock collects every
    pass's times) and the progress callback's ``where`` from one pass to the next (empty: this
    pass makes them)."""
    t_start = time.perf_counter()
    fixed = dict(options.held)
    channels = channel_mask(options.fitted)
    k = len(channels)
    if not inputs.model.metallic:
        channels[3] = 0.0
        fixed.setdefault("metallic", 0.0)
    if options.maps == "none":
        final = (1, 1)
    else:
        res = default_resolution(obs) if options.resolution is None else options.resolution
        final = (int(res), int(res)) if np.isscalar(res) else tuple(int(r) for r in res)
    coarse_to_fine = options.coarse_to_fine and inputs.start is None
    levels = schedule(final, options.level_factor) if coarse_to_fine else [final]
    t_final = final[0] * final[1]
    max_steps = MAX_STEPS if options.max_steps is None else int(options.max_steps)
    pairs_final = neighbour_pairs(final)
    e_final = pairs_final.shape[0]

    if inputs.select_footprint and (inputs.centres is None or obs.samples == 1):
        raise ValueError("select_footprint needs observations with several samples per pixel and their centres")
    if inputs.centres is not None and obs.samples > 1 and per_row(inputs.ibl) and inputs.centre_ibl is None:
        raise ValueError("centres with per-pixel IBL integrals or occlusion factors need centre_ibl: the centres' own")
    mesh = None if options.devices is None else pixel_mesh(options.devices)
    continuation = () if options.continuation is None else tuple(float(w) for w in np.ravel(options.continuation))
    x = None if inputs.start is None else np.asarray(inputs.start, np.float32).reshape(final + (k,))
    history = []
    annealed = footprint = None
    # tables still being built (`PendingTables`): the problems hold their placeholder until the
    # programs the level needs first are compiling
    pending = inputs.ibl if isinstance(inputs.ibl, PendingTables) else None
    tables = inputs.ibl if pending is None else pending.placeholder
    if shared is None:
        shared = {}
    if "runner" not in shared:
        where = dict(level=0, resolution=levels[0])
        cb = None if options.progress is None else (
            lambda step, value, budget: options.progress(dict(
                where, step=int(step), loss=float(value), **({} if budget is None else dict(budget=budget)))))
        compiler = Compiler(dict(compile=0.0, solve=0.0), options.background_compile)
        shared.update(where=where, runner=Runner(options.solver, cb, compiler, options.checkpoint, where))
    # (an executable keeps the callback it was compiled with: a later pass reports through the
    # same one, so it tells that callback where it is through the same `where`)
    where, runner = shared["where"], shared["runner"]
    where.update(level=0, resolution=levels[0])
    compiler = runner.compiler
    clock = compiler.clock
    try:
        for level, shape in enumerate(levels):
            where.update(level=level, resolution=tuple(shape))
            layout = layout_for(obs, shape, options.wrap)
            cov = coverage_counts(layout).reshape(-1)
            t = shape[0] * shape[1]
            seen = np.zeros(t_final, bool)
            seen[:t] = cov > 0
            free = (seen[:, None] * channels[None, :]).astype(np.float32)
            fixed_x = np.broadcast_to(prior(k), (t_final, k)).copy()
            fixed_x[:t] = _fixed_values(fixed, shape, k).reshape(t, k)
            x0 = fixed_x.copy()
            if x is not None:
                up = (x if x.shape[:2] == tuple(shape) else _upsample(x, shape)).reshape(t, k)
                x0[:t] = np.where(channels[None, :] > 0, up, x0[:t])
            x0[:t] = np.where(seen[:t, None], x0[:t], fixed_x[:t])
            last = level == len(levels) - 1
            steps = max_steps if last else min(options.coarse_steps, max_steps)
            head = min(SEARCH_AFTER, steps)
            maps_level = shape != (1, 1)
            searching = last and options.search and maps_level and np.any(channels[3:] > 0) and head < steps
            annealing = (last and maps_level and runner.structured
                         and any(w > 0 for w in continuation) and steps - head >= RELEASED_STEPS)
            prior_on = maps_level and (options.smooth > 0 or annealing)
            pairs, pw = _neighbour_weights(shape, seen, e_final, prior_on)
            problem = with_stencil(Problem(
                obs, layout.index, layout.weight, to_device(free), to_device(pairs), to_device(pw),
                to_device(options.smooth, np.float32), to_device(options.loss_scale, np.float32), tables,
                inputs.model, options.loss, texel_grid(shape, t_final)))
            if mesh is not None:
                problem = shard_problem(problem, mesh)
            early = problem  # the start, the continuation's steps and the search
            grid_start = level == 0 and options.init == "grid" and inputs.start is None
            if inputs.centres is not None and obs.samples > 1 and (last or grid_start):
                lay = layout_for(inputs.centres, shape, options.wrap)
                # the texels the centres see are free here (as in a fit of centres alone); texels only
                # samples read keep their start until the samples' steps, and texels only centres read
                # (where some sample misses the mesh) go back to their fixed values for those steps
                centre_seen = np.zeros(t_final, bool)
                centre_seen[:t] = coverage_counts(lay).reshape(-1) > 0
                c_pairs, c_pw = _neighbour_weights(shape, centre_seen, e_final, prior_on)
                centre_free = (centre_seen[:, None] * channels[None, :]).astype(np.float32)
                early = with_stencil(dataclasses.replace(
                    problem, obs=inputs.centres, index=lay.index, weight=lay.weight, free=to_device(centre_free),
                    pairs=to_device(c_pairs), pair_weight=to_device(c_pw),
                    ibl=inputs.centre_ibl if per_row(tables) else tables))
                if mesh is not None:
                    early = shard_problem(early, mesh)
            num_free = int(np.sum(free))
            x0 = to_device(x0, np.float32)
            if searching:
                searched, classes, search_args = search_inputs(shape, early, SEARCH_ROUNDS, channels[3] > 0)
            selecting = last and inputs.select_footprint
            # compiles this level needs, in the order of their first use, overlap the work before it
            if early is problem or annealing or searching or selecting:  # else only the grid start runs on it
                runner.prefetch(x0, early, num_free)
            if searching:
                compiler.prefetch(searched, coordinate_search, x0, early, classes, *search_args)
            if early is not problem:
                runner.prefetch(x0, problem, num_free)
            grid_key = ("grid",) + problem_key(early)  # (the tables do not change it)
            if pending is not None:  # the grid start's program compiles while the tables are built
                if grid_start:
                    compiler.get(grid_key, grid_initialise, x0, early)
                tables, pending = pending.result(), None
                same = early is problem
                problem = dataclasses.replace(problem, ibl=tables)
                early = problem if same else dataclasses.replace(early, ibl=tables)
            if grid_start:
                announce(options.progress, where, "grid start")
                x0 = to_device(np.asarray(timed(compiler, grid_key, grid_initialise, "init",
                                                 x0, early)), np.float32)
            xs, info = x0, None
            announce(options.progress, where, "solving")
            if annealing:
                jac = runner.jacobian(xs, early, num_free)  # timed as compile and solve
                t0 = time.perf_counter()
                scale = continuation_scale(jac, early)
                clock["init"] = clock.get("init", 0.0) + time.perf_counter() - t0
                weights = [w * scale for w in continuation]
                for w, n in zip(weights, (len(a) for a in np.array_split(np.arange(head), len(weights)))):
                    if n > 0:
                        xs, info = _merge(info, runner(to_device(xs, np.float32),
                                                       with_smooth(early, options.smooth + w), n, num_free))
                annealed = dict(relative=list(continuation), weights=weights, curvature=scale, steps=head,
                                settle_steps=0)
            elif searching:
                xs, info = _merge(info, runner(xs, early, head, num_free))
            done = head if (annealing or searching) else 0
            settle = False
            if searching:
                announce(options.progress, where, "search")
                xn = np.asarray(timed(compiler, searched, coordinate_search, "search", to_device(xs, np.float32),
                                       early, classes, *search_args))
                info["search_moved"] = int(np.sum(np.any(xn[:t] != np.asarray(xs)[:t], axis=1)))
                xs = xn
                settle = annealing and weights[-1] > 0 and steps - done - SETTLE_STEPS >= RELEASED_STEPS
                if settle:
                    annealed["settle_steps"] = SETTLE_STEPS
                announce(options.progress, where, "solving")

            tail = dict(steps=steps - done, num_free=num_free,
                        settle_weight=options.smooth + weights[-1] if settle else None)
            if selecting:  # the same steps at pixel centres first, from the same point
                where["footprint"] = 1
                x_c, info_c, lin_c = _finish_level(runner, early, xs, info, **tail)
                r_c = final_residuals(x_c, early, lin_c)
                where["footprint"] = n_side = samples_side(obs)
            if early is not problem:
                xs = np.where(seen[:, None], xs, fixed_x)
            probing = selecting and runner.structured and tail["steps"] > PROBE_STEPS
            stopped = False
            if probing:  # the samples' first steps, then a look at how well they fit already
                xs, info, linearization = _finish_level(runner, problem, xs, info, **dict(tail, steps=PROBE_STEPS))
                stopped = centres_explain_better(footprint_energies(obs, linearization[0], inputs.centres, r_c))
                if not stopped:
                    xs, info, linearization = _finish_level(runner, problem, xs, info, tail["steps"] - PROBE_STEPS,
                                                            num_free)
            else:
                xs, info, linearization = _finish_level(runner, problem, xs, info, **tail)
            if selecting:
                where.pop("footprint")
                e_samples, e_centres, common = footprint_energies(
                    obs, final_residuals(xs, problem, linearization), inputs.centres, r_c)
                footprint = dict(selected=n_side, energies={str(n_side): e_samples, "1": e_centres}, pixels=common,
                                 steps={str(n_side): info["steps"], "1": info_c["steps"]}, stopped_early=stopped)
                if centres_explain_better((e_samples, e_centres)):
                    footprint["selected"] = 1
                    # texels only samples read are unseen here: their fixed values, as in a fit of centres alone
                    xs, info, linearization = np.where(centre_seen[:, None], x_c, fixed_x), info_c, lin_c
                    obs, problem, seen = inputs.centres, early, centre_seen
            history.append(dict(resolution=list(shape), **info))
            x = xs[:t].reshape(shape + (k,))
        state = StageState(options, runner, compiler, problem, xs, linearization, final, seen, channels, num_free,
                           obs.num_pixels, where, search_on=early)
        entries, stages = run_stages(STAGES, state, clock)
        x = state.xs[:t_final].reshape(final + (k,))
    finally:
        compiler.close()

    result = finish(obs, state, x, inputs.model, options, history, dict(setup=inputs.setup_time, **clock), t_start)
    checks = entries["uniform_check"]
    for name, c in SELECTABLE:  # the value's σ as uncertainty holds it: the kept fit's residual variance
        if checks.get(name, {}).get("uniform"):
            checks[name]["sigma"] = float(np.asarray(result.uncertainty)[..., c][seen[:t_final].reshape(final)][0])
    result.report.update(entries)
    result.report["stages"] = stages
    result.report["steps"] += sum(s["steps"] for s in stages)
    # when each level stops (`pbrfit.fitting.api.fit_observations`), and the robust loss's scale
    result.report["quality"] = options.quality
    result.report["stopping"] = dict(max_steps=int(max_steps), coarse_steps=int(options.coarse_steps),
                                     rtol=float(options.solver.rtol), atol=float(options.solver.atol))
    if options.loss != "l2":
        result.report["loss_scale"] = float(options.loss_scale)
    result.report["continuation"] = annealed
    if runner.structured:
        result.report["cg_rtol"] = float(options.solver.cg_rtol)
        result.report["noise_rtol"] = float(options.solver.noise_rtol)
    if footprint is not None:
        result.report["footprint"] = footprint
    return result, np.asarray(xs, np.float32)[:t_final]


def _neighbour_weights(shape, seen, size: int, on: bool):
    """The smoothness prior's neighbour pairs at this resolution, padded to `size`, and their
    weights: 1 where both texels are seen, else 0 (all 0 when the prior is not `on`)."""
    pairs = np.zeros((size, 2), np.int32)
    weights = np.zeros(size, np.float32)
    if on:
        p = neighbour_pairs(shape)
        pairs[: len(p)] = p
        weights[: len(p)] = (seen[p[:, 0]] & seen[p[:, 1]]).astype(np.float32)
    return pairs, weights


def _finish_level(runner, problem: Problem, x, info, steps: int, num_free: int, settle_weight=None):
    """A level's last `steps` on `problem` from x: the first `SETTLE_STEPS` under the prior
    weight `settle_weight` (unless None), the rest as asked; (x, info, linearisation)."""
    if settle_weight is not None:
        x, info = _merge(info, runner(to_device(x, np.float32), with_smooth(problem, settle_weight), SETTLE_STEPS,
                                      num_free))
        steps -= SETTLE_STEPS
    x, info = _merge(info, runner(to_device(x, np.float32), problem, steps, num_free))
    return x, info, runner.linearization


def continuation_scale(jac, problem: Problem) -> float:
    """The data's mean curvature per fitted texel and channel, in base colour where it is fitted:
    the mean diagonal of the per-texel blocks of JᵀJ (`pbrfit.fitting.normal_matrix.normal_blocks`) over the
    free base-colour channels (else over all free channels); 1 where nothing is free or the
    mean is not a positive number."""
    diag = np.diagonal(np.asarray(jitted_normal_blocks(jac, problem)), axis1=1, axis2=2)
    free = np.asarray(problem.free) > 0
    cols = slice(0, 3) if free[:, :3].any() else slice(None)
    values = diag[:, cols][free[:, cols]]
    scale = float(np.mean(values)) if values.size else 1.0
    return scale if math.isfinite(scale) and scale > 0 else 1.0


def with_smooth(problem: Problem, weight: float) -> Problem:
    """`problem` with the smoothness prior's weight set to `weight` (placed like the old one)."""
    return dataclasses.replace(problem, smooth=jax.device_put(np.float32(weight), problem.smooth.sharding))


def _merge(info: Optional[dict], run) -> tuple:
    """(x, info) of a solver run, its counts added to those of the runs before it on this level."""
    x, more = run
    if info is not None:
        for count in ("steps", "accepted", "cg_iterations"):  # counts add up; the rest is the last run's
            if count in info:
                more[count] += info[count]
        if "search_moved" in info:
            more["search_moved"] = info["search_moved"]
    return x, more
