"""XLA compile options pbrfit's programs choose, and compiling with them.

XLA's CPU backend generates a fused loop's code with its fusion emitters by default; without
them (``xla_cpu_use_fusion_emitters=False``, the element-wise emitter it used before) it compiles
a program about 40% sooner, and the program runs about as fast on a small problem and up to
twice as slow on a large one (experiments/speed.md, "cheaper compiles for small fits"). The
programs of a small fit (`pbrfit.fitting.runner.small_problem`) and the gradient check's, which
run for less time than they take to compile, are compiled with `FAST_COMPILE`.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, Mapping

__all__ = ["FAST_COMPILE", "compile_lowered", "jit_choosing"]

#: XLA options that compile a program sooner for about the same speed on small problems.
FAST_COMPILE: Mapping[str, Any] = {"xla_cpu_use_fusion_emitters": False}


def compile_lowered(lowered, options: Mapping[str, Any]):
    """``lowered.compile(options)`` (a `jax.stages.Lowered`), or with XLA's defaults where this
    XLA build does not know one of the options (the fusion emitters are a CPU option of recent
    releases)."""
    if not options:
        return lowered.compile()
    try:
        return lowered.compile(dict(options))
    except Exception as error:  # jax's JaxRuntimeError: INVALID_ARGUMENT: No such compile option
        if not _unknown_option(error):
            raise
        return lowered.compile()


def _unknown_option(error: Exception) -> bool:
    return "No such compile option" in str(error)


def jit_choosing(fn: Callable, fast_when: Callable[[tuple], bool], **jit_kwargs) -> Callable:
    """``fn`` jitted twice (`jax.jit` with ``jit_kwargs``), with XLA's defaults and with
    `FAST_COMPILE`: a call runs the second where ``fast_when(args)`` (its positional arguments)
    holds, the first where not, where this XLA build does not know the options, or inside another
    function's trace (options belong to the outermost program). The two are the wrapper's
    ``variants`` (full, fast)."""
    import jax

    full = jax.jit(fn, **jit_kwargs)
    fast = jax.jit(fn, compiler_options=dict(FAST_COMPILE), **jit_kwargs)
    known = [True]

    @functools.wraps(fn)
    def call(*args):
        if known[0] and fast_when(args) and not any(isinstance(a, jax.core.Tracer)
                                                    for a in jax.tree_util.tree_leaves(args)):
            try:
                return fast(*args)
            except Exception as error:  # jax's JaxRuntimeError
                if not _unknown_option(error):
                    raise
                known[0] = False
        return full(*args)

    call.variants = (full, fast)
    return call
