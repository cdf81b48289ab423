"""Shared test settings.

- A small, deterministic hypothesis profile (the machine is shared).
- A cache folder of the session's own (``PBRFIT_CACHE``), removed at exit: the CLI's G-buffer
  and XLA caches never read or write the user's ``~/.cache/pbrfit``, so no test depends on what
  earlier runs left there (a fresh CI machine has nothing there).
- JAX's persistent compilation cache in that folder, on from the start, as ``pbrfit`` turns it on
  for its commands (`pbrfit.cli.main`): a test that builds a new ``jax.jit`` of a function another
  test compiled at the same shapes loads the executable instead of compiling it again (JAX keeps
  no program with a host callback, such as a solve that reports progress). JAX opens the cache
  folder at the first compile and keeps it: a CLI command run in a test later sets the option
  to its own folder, which changes nothing.
"""

import atexit
import os
import shutil
import tempfile

import pbrfit  # noqa: F401  (first: sets XLA workarounds before any JAX backend starts)

import jax
from hypothesis import HealthCheck, settings

settings.register_profile(
    "pbrfit",
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("pbrfit")

_CACHE = tempfile.mkdtemp(prefix="pbrfit-test-cache-")  # one per process (each xdist worker)
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
os.environ["PBRFIT_CACHE"] = _CACHE
jax.config.update("jax_compilation_cache_dir", os.path.join(_CACHE, "xla"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)  # as `pbrfit.cli.main` sets it
