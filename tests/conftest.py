"""Shared test settings: a small, deterministic hypothesis profile (the machine is shared)."""

import pbrfit  # noqa: F401  (first: sets XLA workarounds before any JAX backend starts)

from hypothesis import HealthCheck, settings

settings.register_profile(
    "pbrfit",
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("pbrfit")
