"""Solver runs compiled ahead of time, and the jitted evaluations a fit's passes share.

`Runner` runs the fit's solver, an optimistix solver object (the structured one,
`pbrfit.fitting.solvers.structured.StructuredLM`, or any other, `pbrfit.fitting.solvers.optx`),
through `optx.least_squares` on a `pbrfit.fitting.objective.Problem`, compiled once per problem
shape by `Compiler`, which can compile in a background thread while the fit does other work and
keeps compile time apart from run time. `timed` runs any other jitted pass (the grid start, the
coordinate search) the same way.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import itertools
import operator
import time
from pathlib import Path
from typing import Mapping, Optional

import equinox as eqx
import filelock
import jax
import numpy as np

from .solvers.optx import for_size, optx_solve
from .objective import Problem, objective
from .sharding import (halving_sizes, mesh_size, moving_pixels, set_texel_rows, take_pixels, take_texels,
                       texel_program, texel_rows)
from .stencil import data_blocks, data_neighbour_blocks, stencil_covers
from .solvers import structured
from .checkpoint import call_id
from .initialisation import classes_share_no_pixel, coordinate_search, parity_classes
from ..io.atomic import hold_on_abandon
from ..transfer import to_device
from ..xla import FAST_COMPILE, compile_lowered, jit_choosing

__all__ = ["announce", "enable_compilation_cache", "stamp_cache_entries", "Compiler", "PendingTables", "Runner",
           "timed", "timed_rest", "thread_time", "problem_key", "compile_summary", "compile_options", "small_problem",
           "fit_jit", "FAST_COMPILE_ROWS", "SEARCH_FAST_COMPILE_ROWS", "jitted_normal_blocks", "jitted_neighbour_blocks",
           "problem_energy"]

#: With a checkpoint, the structured solver's runs go in parts of about
#: `pbrfit.fitting.checkpoint.CHECKPOINT_SECONDS`, at the speed the last part ran, and of at least
#: this many steps (the fit's first part, before the speed is known, too): each part after the
#: first linearises once more, about half a step's time (peer-plane, 32 x 32 maps), so the parts
#: cost at most about 5 % more (where a run is cut does not change its steps: `structured.LMCarry`).
MIN_PART_STEPS = 10
#: Compiles shorter than this are not kept on disk. Loading a program that compiles in 0.1 s is
#: faster than compiling it, and a fit's small ones add up (peer scene, warm command: 6.6 s with
#: only compiles over 0.5 s kept, 6.0 s with all over 0.05 s, 9 of its 13 programs); the few
#: shorter ones (type conversions) are left out, as each entry kept makes every later write scan
#: the folder (JAX's size limit, `COMPILATION_CACHE_BYTES`): keeping every compile made the test
#: suite 860 s instead of 700 (1,400 of its programs compile in over 0.05 s).
MIN_CACHED_COMPILE_SECONDS = 0.05
#: The persistent compilation cache's size: the oldest executables are evicted beyond it. A size
#: also makes JAX lock the folder (``filelock``) for each read and write, so processes that share
#: it (two fits at once, a test suite's workers) never read an executable another is writing.
COMPILATION_CACHE_BYTES = 2 * 1024**3
#: The file in the cache folder that JAX locks around each read and write of an entry
#: (``jax._src.lru_cache.LRUCache``). JAX writes an entry in place, not under a temporary name, so a
#: process ended by a signal takes this lock before it ends (`pbrfit.io.atomic.abandon_writes`):
#: it never ends halfway through an executable, which later runs would read as a corrupt entry.
JAX_CACHE_LOCK_FILE = ".lockfile"


def stamp_cache_entries(folder) -> None:
    """Give each executable in ``folder`` that has no access time (written by a JAX without
    eviction, e.g. an earlier pbrfit) one, its file's modification time: a sized cache evicts by
    them and fails to write beside an entry that lacks one."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    for entry in folder.glob("*-cache"):
        stamp = entry.with_name(entry.name[: -len("-cache")] + "-atime")
        if not stamp.exists():
            stamp.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))


def enable_compilation_cache(folder) -> None:
    """Keep XLA executables in ``folder`` (JAX's persistent compilation cache), shared safely by
    the processes that use it. JAX opens the folder at its first compile and keeps it. A process
    ended by a signal waits for an entry being written (`JAX_CACHE_LOCK_FILE`)."""
    stamp_cache_entries(folder)
    hold_on_abandon("compilation cache", filelock.FileLock(str(Path(folder) / JAX_CACHE_LOCK_FILE)))
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_CACHED_COMPILE_SECONDS)
    jax.config.update("jax_compilation_cache_max_size", COMPILATION_CACHE_BYTES)


def announce(progress, where: dict, stage: str) -> None:
    """Tell a fit's ``progress`` callback (or None) that `stage` begins: ``{stage, **where}``
    (the level and resolution, and the pass it is in), so that a display says where the fit is
    between the solver's steps, which are reported only when each run ends."""
    if progress is not None:
        progress(dict(where, stage=stage))


def problem_energy(residuals, x, problem: Problem) -> float:
    """The objective at x from its residuals (the prior's term evaluated where it is on)."""
    if float(problem.smooth) > 0:
        return float(jax.jit(objective)(to_device(x, np.float32), problem))
    return 0.5 * float(np.sum(np.square(np.asarray(residuals, np.float64))))


#: A fit program over fewer sample rows than this is compiled with `pbrfit.xla.FAST_COMPILE` (on
#: the CPU): its runs are short next to its compile. On a 2-core CPU the peer scene (59,530 rows)
#: compiled its grid start and solver in 4.1 s instead of 6.4, at the same step times; the flash
#: capture's solver (552,000 rows) ran twice as slowly without XLA's fusion emitters.
FAST_COMPILE_ROWS = 2**17
#: ... and the coordinate search, which runs about 30% slower without them (the peer scene's 0.48
#: to 0.59 s against 0.68), from a quarter of those rows: a fit's search over all of a small
#: scene's pixels keeps XLA's defaults (it compiles while the solve runs), a repair's over the few
#: pixels of the texels it moves compiles sooner.
SEARCH_FAST_COMPILE_ROWS = FAST_COMPILE_ROWS // 4


def small_problem(args, rows: Optional[int] = None) -> bool:
    """Whether a fit program run on ``args`` compiles with `FAST_COMPILE`: where its largest
    `Problem` has fewer than ``rows`` (default `FAST_COMPILE_ROWS`) sample rows and it runs on
    the CPU."""
    counts = [a.obs.num_rows for a in args if isinstance(a, Problem)]
    limit = FAST_COMPILE_ROWS if rows is None else rows
    return bool(counts) and max(counts) < limit and jax.default_backend() == "cpu"


def compile_options(fn, args) -> dict:
    """The XLA options of the fit program ``fn`` run on ``args`` (`small_problem`, below
    `SEARCH_FAST_COMPILE_ROWS` for the coordinate search)."""
    rows = SEARCH_FAST_COMPILE_ROWS if fn is coordinate_search else FAST_COMPILE_ROWS
    return dict(FAST_COMPILE) if small_problem(args, rows) else {}


def fit_jit(fn, **jit_kwargs):
    """``fn`` jitted (`jax.jit`), compiled with `FAST_COMPILE` where its arguments are a
    `small_problem`'s (`pbrfit.xla.jit_choosing`)."""
    return jit_choosing(fn, small_problem, **jit_kwargs)


def _compile(fn, args, kwargs):
    return compile_lowered(fn.lower(*args, **kwargs), compile_options(fn, args))


_data_blocks = fit_jit(data_blocks, static_argnums=2)


def jitted_normal_blocks(jac, problem: Problem):
    """The per-texel blocks of JᵀJ (`pbrfit.fitting.stencil.data_blocks`), one jitted function for
    the repair, the uniform check, the preconditioner's scale and the uncertainty (one compile per
    problem shape): by stencil where `stencil_covers` the problem's map."""
    return _data_blocks(jac, problem, stencil_covers(problem))


#: The blocks between neighbouring texels (`pbrfit.fitting.stencil.data_neighbour_blocks`), for the
#: uncertainty's windows (one compile per map size).
jitted_neighbour_blocks = fit_jit(data_neighbour_blocks, static_argnums=2)


class Compiler:
    """Ahead-of-time compilation, timed apart from the runs, each executable compiled once per key.

    `prefetch` starts a compile in a background thread as soon as the arguments' shapes are
    known, so that it overlaps the work before its first use (compiling is mostly single-threaded,
    so a second core is idle meanwhile); `get` returns the executable, waiting for it if needed.
    The thread compiles under the caller's default device, matmul precision and x64 setting
    (JAX's contexts for them are thread-local). ``clock["compile"]`` gets the time the fit waits
    for compiles, ``clock["compile_background"]`` the compile time the thread spent while the fit
    did other work (its compile time less the wait)."""

    def __init__(self, clock: dict, background: bool = True):
        self.clock, self.background = clock, background
        self.clock.setdefault("compile", 0.0)
        self.executor = None
        self.pending, self.done = {}, {}

    def has(self, key) -> bool:
        """Whether the executable of `key` is compiled or being compiled."""
        return key in self.done or key in self.pending

    def prefetch(self, key, fn, *args, **kwargs) -> None:
        if not self.background or self.has(key):
            return
        if self.executor is None:
            self.executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pbrfit-compile")
        context = _caller_context()

        def work():
            with context():
                t0 = time.perf_counter()
                compiled = _compile(fn, args, kwargs)
                return compiled, time.perf_counter() - t0

        self.pending[key] = self.executor.submit(work)

    def get(self, key, fn, *args, **kwargs):
        if key in self.done:
            return self.done[key]
        t0 = time.perf_counter()
        future = self.pending.pop(key, None)
        if future is None:
            compiled = _compile(fn, args, kwargs)
        else:
            compiled, took = future.result()
            overlapped = max(took - (time.perf_counter() - t0), 0.0)
            self.clock["compile_background"] = self.clock.get("compile_background", 0.0) + overlapped
        self.clock["compile"] += time.perf_counter() - t0
        self.done[key] = compiled
        return compiled

    def close(self) -> None:
        """Stop: compiles not started are dropped; a running one finishes in its thread, unwaited."""
        if self.executor is not None:
            self.executor.shutdown(wait=False, cancel_futures=True)
            self.executor = None
        self.pending.clear()


def _caller_context():
    """A context manager factory that sets, in another thread, the calling thread's default device,
    matmul precision and x64 setting (JAX's contexts for them are thread-local)."""
    config = jax.config
    device, precision, x64 = (config.jax_default_device, config.jax_default_matmul_precision,
                              config.jax_enable_x64)

    @contextlib.contextmanager
    def context():
        with jax.default_device(device), jax.default_matmul_precision(precision), jax.enable_x64(x64):
            yield

    return context


@dataclasses.dataclass(frozen=True, eq=False)
class PendingTables:
    """Tables (a pytree of arrays: the split sum's, `pbrfit.render.views.capture_ibl`) being built
    in a thread of their own, so that a fit compiles its programs meanwhile: their structure and
    shapes are known at once (`jax.eval_shape`), and ``placeholder`` (zeros of those shapes) serves
    to lower and compile the programs that read them; `result` waits for the tables. On `pbrfit
    demo`'s capture the tables took 3.9 s of a cold fit (1.5 + 0.5 s of it compiling) before
    the fit's first compile started (experiments/speed.md)."""

    placeholder: object
    future: concurrent.futures.Future

    @classmethod
    def start(cls, build) -> "PendingTables":
        """Build ``build()`` in a thread; returns once its shapes are known. An error in ``build``
        is raised here when tracing finds it, else by `result`."""
        context = _caller_context()
        shapes = concurrent.futures.Future()

        def work():
            with context():
                try:
                    shapes.set_result(jax.eval_shape(build))
                except BaseException as err:
                    shapes.set_exception(err)
                    raise
                t0 = time.perf_counter()
                return jax.block_until_ready(build()), time.perf_counter() - t0

        executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pbrfit-tables")
        future = executor.submit(work)
        executor.shutdown(wait=False)
        placeholder = jax.tree.map(lambda a: np.zeros(a.shape, a.dtype), shapes.result())
        return cls(placeholder, future)

    def result(self):
        """The tables, once built."""
        return self.future.result()[0]

    @property
    def seconds(self) -> float:
        """How long the build took in its thread (once `result` has returned)."""
        return self.future.result()[1]


def compile_summary(times: Mapping[str, float]) -> str:
    """A report's compile times in words: waited for, and compiled meanwhile in the background."""
    text = f"compile {times.get('compile', 0.0):.1f} s"
    if times.get("compile_background", 0.0) > 0.0:
        text += f", {times['compile_background']:.1f} s more overlapped"
    return text


def problem_key(problem: Problem, pixels: Optional[int] = None, left_out: bool = False,
                texels: Optional[int] = None) -> tuple:
    """What an executable over `problem` is specialised to: rows per pixel, the shapes, whether it
    has a ``grid``, whether the structured solver's products go by stencil, whether it leaves
    pixels out (`pbrfit.fitting.objective.LeftOut`) and how many texels its conjugate gradients
    run over (`Problem.texels`, None: all); with ``pixels`` (and ``left_out``, ``texels``), that
    of `problem` over so many pixels (`pbrfit.fitting.sharding.take_pixels`)."""
    rows = problem.index.shape[0] if pixels is None else pixels * problem.samples
    if texels is None and problem.texels is not None:
        texels = int(problem.texels.shape[0])
    return (problem.obs.samples, (rows,) + tuple(problem.index.shape[1:]), tuple(problem.free.shape),
            tuple(problem.pairs.shape), problem.grid is not None, problem.stencil is not None,
            left_out or problem.left_out is not None, texels)


def search_inputs(shape, problem: Problem, rounds: int, blend: bool) -> tuple:
    """(key, classes, arguments after them) of a `coordinate_search` at map ``shape``: the key of
    its executable (``("coordinate_search", shape, separable) + problem_key(problem)``), one for
    the fit's search and its repair (the rounds are an argument, an int32
    array; whether classes share pixels, `classes_share_no_pixel`, is static), the parity classes
    on the device, and (rounds, blend, separable)."""
    classes = parity_classes(shape)
    separable = classes_share_no_pixel(problem, classes)
    key = ("coordinate_search", tuple(shape), separable) + problem_key(problem)
    return key, to_device(classes), (to_device(rounds, np.int32), bool(blend), separable)


#: A re-fit of a few texels over the pixels that read them (`Runner.refit`) pays for a program of
#: its own: its compile costs about as much as the solver's steps over this many sample rows (on a
#: 2-core CPU, 3 to 6 s: 90 steps of `pbrfit demo`'s 41,234 pixels, 8 of a 256² map's 636k, one
#: row each; a step's time grows with its rows, a compile's does not).
REFIT_COMPILE_ROW_STEPS = 4_000_000


@jax.jit
def _put_rows(full, at, part):
    """``full`` with its rows ``at`` set to ``part``'s (an index past its end: that row dropped)."""
    return full.at[at].set(part, mode="drop")


def _sample_rows(pixels, samples: int):
    """The sample rows of ``pixels`` (indices; one past the last pixel gives rows past the last)."""
    return (np.asarray(pixels, np.int32)[:, None] * samples + np.arange(samples, dtype=np.int32)).reshape(-1)


def pixel_rows_from(source, pixels, linearization, samples: int):
    """``linearization`` (a problem's pixel residuals (P, 3) and per-row Jacobians (P ``samples``,
    3, K)) with the rows of ``pixels`` (indices) taken from ``source``, the same problem's at
    other texel values: where those pixels read no texel on which the two differ, the problem's
    linearisation at ``source``'s texels for them and at ``linearization``'s for the others."""
    pixels = np.asarray(pixels, np.int32)
    rows = _sample_rows(pixels, samples)
    return (_put_rows(linearization[0], pixels, source[0][pixels]),
            _put_rows(linearization[1], rows, source[1][rows]))


#: Clock entries that are not time on the fit's own thread (`Compiler`'s overlapped compiles).
_OFF_THREAD = ("compile_background",)


def thread_time(clock: Mapping[str, float]) -> float:
    """The time ``clock``'s entries spent on the fit's own thread (all but `Compiler`'s overlapped
    compiles, which ran beside it)."""
    return sum(v for k, v in clock.items() if k not in _OFF_THREAD)


@contextlib.contextmanager
def timed_rest(clock: dict, name: str):
    """Add to ``clock[name]`` the wall time of the block that no other entry of ``clock`` took
    meanwhile: a stage's own work (its host-side steps and jitted evaluations compiled on first
    use), with its solver steps, searches and waited-for compiles counted where they are."""
    before, t0 = thread_time(clock), time.perf_counter()
    try:
        yield
    finally:
        rest = (time.perf_counter() - t0) - (thread_time(clock) - before)
        clock[name] = clock.get(name, 0.0) + max(rest, 0.0)


def timed(compiler: Compiler, key, fn, name: str, *args):
    """Run `fn` compiled ahead of time (`Compiler.get`) and add the run time to ``clock[name]``."""
    compiled = compiler.get(key, fn, *args)
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    compiler.clock[name] = compiler.clock.get(name, 0.0) + time.perf_counter() - t0
    return out


#: The structured solver's tolerances, which its runs take as arrays (not static values).
_TOLERANCES = operator.attrgetter("rtol", "atol", "cg_rtol", "noise_rtol")


class Runner:
    """Runs a solver (an optimistix solver object), compiled ahead of time once per problem shape
    (`Compiler`): once per fit, or twice when the start runs on pixel centres
    (`pbrfit.fitting.api.fit_observations`). The structured solver takes its step budget as an
    argument; any other solver is also compiled once per step budget (optimistix's loop length is
    static). ``progress(k, E, budget)`` gets the structured solver's E at each step k after its
    solve (so its program holds no host callback and can be cached), with the run's step budget,
    and another solver's at each evaluation k of the objective, as they happen (budget None).

    With a ``checkpoint`` (`pbrfit.fitting.checkpoint.Checkpoint`) each run is journaled, a run the
    checkpoint holds is replayed, not solved, and the structured solver runs in parts of about
    ``checkpoint.seconds`` (`pbrfit.fitting.solvers.structured.LMCarry`: the same steps, bit for bit),
    its state kept after a part; ``where`` (the progress callback's) says where a resumed fit went on."""

    def __init__(self, solver, progress, compiler: Compiler, checkpoint=None, where=None):
        if isinstance(solver, structured.StructuredLM):
            # the tolerances as arrays: one executable serves every tolerance (each quality rung)
            solver = eqx.tree_at(_TOLERANCES, solver, [to_device(t, np.float32) for t in _TOLERANCES(solver)])
        self.solver, self.progress, self.compiler = solver, progress, compiler
        self.checkpoint, self.where = checkpoint, {} if where is None else where
        self.clock = compiler.clock
        self._reported = []
        self._budget = None  # the structured run's step budget, which its progress entries carry
        self._lazy = None  # (x, problem, num_free) of a replayed run, linearised when asked
        self._linearization = None
        self._step_seconds = None  # a structured step's seconds, as the last part of a run took
        self._start = structured.LMCarry.start() if self.structured else None
        # an optimistix solver reports each evaluation of the objective, numbered here from 0 in
        # every run (one lambda per runner: the compiled solve keeps the one it was traced with)
        self.evaluations = itertools.count()
        self.tick = None if progress is None else (lambda value: self._report(next(self.evaluations), value))

    @property
    def structured(self) -> bool:
        return isinstance(self.solver, structured.StructuredLM)

    @property
    def linearization(self):
        """(residuals, per-row Jacobians) at the last run's x (the structured solver's; None for
        another): a replayed run's are the solver's step 0 at its x, the same numbers."""
        if self._lazy is not None:
            x, problem, num_free = self._lazy
            self._lazy = None
            key, fn, args, _ = self._call(to_device(x, np.float32), problem, 0, num_free)
            out = self._timed_run(key, fn, args)
            self._linearization = (out[2], out[3])
        return self._linearization

    def _report(self, k, value) -> None:
        self._reported.append((k, value))
        if self.progress is not None:
            self.progress(k, value, self._budget)

    def _call(self, x0, problem, steps, num_free, carry=None):
        """(key, fn, args, solver run) of a run."""
        if self.structured:
            args = (x0, problem, self.solver, to_device(steps, np.int32), self._start if carry is None else carry)
            return ("structured",) + problem_key(problem), structured.solve, args, self.solver
        opt = for_size(self.solver, num_free)
        key = (type(opt).__name__, steps) + problem_key(problem)
        return key, optx_solve, (x0, problem, opt, steps, self.tick), opt

    def _timed_run(self, key, fn, args):
        compiled = self.compiler.get(key, fn, *args)
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        self.clock["solve"] += time.perf_counter() - t0
        return out

    def prefetch(self, x0, problem, num_free) -> None:
        """Start compiling the structured solver for `problem` in the background (its step
        budget is an argument; another solver's is not known yet, so it is not)."""
        if self.structured:
            key, fn, args, _ = self._call(x0, problem, 0, num_free)
            self.compiler.prefetch(key, fn, *args)

    def __call__(self, x0, problem, steps, num_free):
        self.evaluations = itertools.count()
        self._reported = []
        # the steps a structured run may take (an optimistix solver's entries count evaluations)
        self._budget = int(steps) if self.structured else None
        number = ident = None  # the run's number in the fit and its identity, with a checkpoint
        if self.checkpoint is not None:
            number = self.checkpoint.next_run()
            ident = call_id(number, x0, problem, steps)
            replayed = self.checkpoint.replay(number, ident, self.where)
            if replayed is not None:
                x, info, reported = replayed
                for k, value in reported:
                    self._report(k, value)
                self._lazy, self._linearization = ((x, problem, num_free) if self.structured else None), None
                return x, info
        self._lazy = None
        if self.structured:
            x, info = self._structured(x0, problem, steps, num_free, number, ident)
        else:
            key, fn, args, opt = self._call(x0, problem, steps, num_free)
            out = self._timed_run(key, fn, args)
            x = np.asarray(out[0])
            info = dict(steps=int(out[1]), result=int(out[2]), method=type(opt).__name__)
            self._linearization = None
        if self.checkpoint is not None:
            self.checkpoint.record(number, ident, x, info, self._reported)
        return x, info

    def _part_steps(self) -> int:
        """Steps in a part of a structured run: about the checkpoint's seconds, at the speed of the
        last part, and at least `MIN_PART_STEPS`."""
        if self._step_seconds is None:
            return MIN_PART_STEPS
        return max(MIN_PART_STEPS, int(self.checkpoint.seconds / max(self._step_seconds, 1e-9)))

    def _structured(self, x, problem, steps, num_free, number, ident):
        """The structured solver's run: at once, or with a checkpoint in parts of about its
        ``seconds`` each (`_part_steps`), the state kept after each (from the checkpoint's partial
        run where it holds this one)."""
        carry, done, part = None, 0, steps
        if self.checkpoint is not None:  # parts of about its seconds at the speed of the last part
            part = self._part_steps()
            kept = self.checkpoint.partial_run(number, ident)
            if kept is not None:  # what it had reported, again, and on from there
                x, arrays = kept
                carry = structured.LMCarry(**{name: to_device(v) for name, v in arrays.items()})
                done = int(arrays["k"]) - 1
                for k, value in enumerate(np.asarray(arrays["history"])[: done + 1]):
                    self._report(k, value)
        x = to_device(x, np.float32)
        while True:
            solving = self.clock["solve"]
            key, fn, args, _ = self._call(x, problem, min(steps, done + part), num_free, carry)
            out = self._timed_run(key, fn, args)
            s = out[1]
            before, done = done, int(s.steps)
            history = np.asarray(s.history)
            first = 0 if carry is None else before + 1
            for k in range(first, min(done + 1, len(history))):
                self._report(k, history[k])
            if done > before:
                self._step_seconds = (self.clock["solve"] - solving) / (done - before)
            # ended: a stopping test, the budget, or a part that took no step (a start the solver
            # cannot leave, e.g. a NaN loss: every later part would take none either)
            if bool(s.stopped) or done >= steps or done <= before:
                break
            x, carry = out[0], structured.LMCarry.after(s)
            part = self._part_steps()
            self.checkpoint.save_partial(number, ident, x, done, {
                field.name: getattr(carry, field.name) for field in dataclasses.fields(carry)})
        self._linearization = (out[2], out[3])
        return np.asarray(out[0]), dict(steps=done, accepted=int(s.accepted), cg_iterations=int(s.cg_iterations))

    def refit(self, x0, problem: Problem, moving, steps: int, num_free: int, linearization):
        """`steps` steps of the structured solver from x0 on ``problem``, whose free channels are
        those of the texels of ``moving`` (T,) alone, ``linearization`` its (residuals, per-row
        Jacobians) where the other texels stand (they stay there): over the pixels that read
        those texels (`pbrfit.fitting.sharding.moving_pixels`), padded to 1/2, 1/4, ... of them
        (`pbrfit.fitting.sharding.take_pixels`, the other pixels' term kept, so that the solve
        stops where one over every pixel would) and over the texels those read
        (`pbrfit.fitting.sharding.take_texels`), or over every pixel, whichever costs fewer
        row-steps (sample rows times steps): each size's program not compiled yet counts
        `REFIT_COMPILE_ROW_STEPS`.
        Over some pixels, the conjugate gradients of a problem held by stencil run over the
        texels with a free channel alone (`Problem.texels`, padded to 1/2, 1/4, ... of the
        texels taken), and the whole problem's linearisation at the result is ``linearization``
        with those pixels' rows replaced. Returns what a call returns; `linearization` is
        ``problem``'s."""
        total, samples = problem.num_pixels, problem.samples
        if not self.structured:
            return self(x0, problem, steps, num_free)
        moving = np.asarray(moving, bool)
        pixels = moving_pixels(moving, np.asarray(problem.index), np.asarray(problem.weight), samples)
        sizes = halving_sizes(total, len(pixels), mesh_size(problem))
        if len(sizes) == 1:
            return self(x0, problem, steps, num_free)

        def taken(size, count=None):
            """(problem over ``size`` pixels and ``count`` texels (default: the least) holding
            theirs, which texel each is)."""
            sub, texels = take_texels(take_pixels(problem, pixels, size, linearization[0]), np.asarray(x0), count)
            if sub.stencil is not None:  # conjugate gradients over the free texels alone
                free = np.flatnonzero(np.any(np.asarray(sub.free) > 0, axis=1))
                count = halving_sizes(sub.num_texels, len(free), 1)[-1]
                padded = np.concatenate([free, np.full(count - len(free), sub.num_texels)]).astype(np.int32)
                sub = dataclasses.replace(sub, texels=jax.device_put(padded, sub.free.sharding))
            return sub, texels

        # the texels taken do not depend on the size: the smallest's problem gives every size's key,
        # its texels padded to a count whose program is compiled where there is one (`texel_program`)
        least = taken(sizes[-1])
        programs = [texel_program(problem, least[0], lambda p, n=size: ("structured",) + problem_key(p, n),
                                  self.compiler.has) for size in sizes[1:]]
        cost = [steps * total * samples] + [
            steps * size * samples + (0 if self.compiler.has(k) else REFIT_COMPILE_ROW_STEPS)
            for size, (_, k) in zip(sizes[1:], programs)]
        best = int(np.argmin(cost))
        if best == 0:
            return self(x0, problem, steps, num_free)
        size, count = sizes[best], programs[best - 1][0]
        sub, texels = least if best == len(sizes) - 1 and count == least[0].num_texels else taken(size, count)
        x, info = self(to_device(texel_rows(x0, texels), np.float32), sub, steps, num_free)
        # the rows of the pixels taken (padding: past the end, dropped)
        at = np.concatenate([pixels, np.full(size - len(pixels), total)]).astype(np.int32)
        r, jac = self.linearization
        self._linearization = (_put_rows(linearization[0], at, r),
                               _put_rows(linearization[1], _sample_rows(at, samples), jac))
        return set_texel_rows(np.asarray(x0, np.float32), texels, x), info

    def jacobian(self, x, problem, num_free):
        """Per-pixel Jacobians (P, 3, K) at x: the structured solver's step 0, which only
        linearises (compiled already for the solve)."""
        self(x, problem, 0, num_free)
        return self.linearization[1]
