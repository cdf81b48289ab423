"""The knobs of environment light that a fit is given (``ibl_settings``, ``occlusion``), as plain
frozen dataclasses and names with no JAX, so that the command line's parser, which shows their
defaults in ``pbrfit fit --help``, loads none. `pbrfit.lighting.pixel_ibl` and
`pbrfit.lighting.visibility` use them (and re-export them)."""

from __future__ import annotations

import dataclasses

__all__ = ["PixelIBLSettings", "MIN_LEVELS", "MIN_SAMPLES", "MAX_LEVELS", "MAX_SAMPLES", "OCCLUSION_MODES"]

#: The fewest roughness levels (a spline needs two nodes) and sample steps `PixelIBLSettings` takes.
MIN_LEVELS = 2
MIN_SAMPLES = 1
#: ... and the most: far beyond any use, and within the int32 counters of the jitted loops
#: (`pbrfit fit --ibl-levels`, `--ibl-samples`; `pbrfit synth --ibl-samples` for its Monte Carlo
#: renders).
MAX_LEVELS = 256
MAX_SAMPLES = 1 << 20


@dataclasses.dataclass(frozen=True)
class PixelIBLSettings:
    """Knobs of the per-pixel integrals; defaults chosen by `experiments/ibl_accuracy.py` (17
    levels: 9 are 2 to 3 times worse at n·v 0.1-0.3, 33 no better) and `experiments/env_fits.py`
    (512 samples: on sphere-env rendered by the Monte Carlo reference, 128 samples leave a
    well-observed roughness RMSE of 0.112 where 512 reach 0.069; `experiments/results/env_fits.json`).

    Attributes:
        levels: roughness grid r_j = j / (levels - 1), j = 0 .. levels - 1.
        samples: sample steps per pixel (each: one environment, one cosine and, per level, one
            visible-normal direction); the error of I_k falls roughly as 1/sqrt(samples).
        seed: seed of each pixel's random shift of its quasi-random sequence.
    """

    levels: int = 17
    samples: int = 512
    seed: int = 0

    def __post_init__(self):
        if not MIN_LEVELS <= int(self.levels) <= MAX_LEVELS:
            raise ValueError(f"PixelIBLSettings.levels must be from {MIN_LEVELS} to {MAX_LEVELS}, got {self.levels!r}")
        if not MIN_SAMPLES <= int(self.samples) <= MAX_SAMPLES:
            raise ValueError(f"PixelIBLSettings.samples must be from {MIN_SAMPLES} to {MAX_SAMPLES}, "
                             f"got {self.samples!r}")


#: ``occlusion=``: "off", "auto" (on where the mesh blocks a meaningful share of the environment
#: light, `pbrfit.lighting.visibility.OcclusionSettings.auto_share`) or "on"
#: (`pbrfit.FitOptions.occlusion` holds the default).
OCCLUSION_MODES = ("off", "auto", "on")

#: ``OcclusionSettings.bounce``: whether blocked directions bring the light the capture shows on
#: the surface they hit: "auto" (fit with and without it, keep the fit of lower residual σ),
#: "on" or "off" (`pbrfit.lighting.visibility`).
BOUNCE_MODES = ("auto", "on", "off")
