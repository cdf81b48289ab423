"""Shared test settings.

- A small, deterministic hypothesis profile (the machine is shared).
- A cache folder of the run's own (``PBRFIT_CACHE``), shared by the xdist workers of one run
  (``PBRFIT_TEST_CACHE``) and removed when the run ends: the CLI's G-buffer and XLA caches
  never read or write the user's ``~/.cache/pbrfit``, so no test depends on what earlier runs
  left there (a fresh CI machine has nothing there).
- JAX's persistent compilation cache in that folder, on from the start, as ``pbrfit`` turns it on
  for its commands (`pbrfit.fitting.runner.enable_compilation_cache`, which locks it for the
  workers): a test that builds a new ``jax.jit`` of a function another test (in any worker, or a
  command's subprocess) compiled at the same shapes loads the executable instead of compiling it
  again.
"""

import atexit
import os
import shutil
import tempfile

import pbrfit  # noqa: F401  (first: sets XLA workarounds before any JAX backend starts)

from hypothesis import HealthCheck, settings

from pbrfit.fitting.runner import enable_compilation_cache

settings.register_profile(
    "pbrfit",
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("pbrfit")

# The run's first process (xdist's controller, or a run without workers) makes the folder and
# removes it at exit; the workers it starts inherit the variable and share the folder.
_CACHE = os.environ.get("PBRFIT_TEST_CACHE")
if _CACHE is None:
    _CACHE = os.environ["PBRFIT_TEST_CACHE"] = tempfile.mkdtemp(prefix="pbrfit-test-cache-")
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
os.environ["PBRFIT_CACHE"] = _CACHE
enable_compilation_cache(os.path.join(_CACHE, "xla"))
