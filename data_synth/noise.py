"""Sensor effects: supersampling, image noise and quantisation (numpy, seeded).

The order a synthetic capture applies them in is the order a camera does: the scene is
rendered at k times the resolution and box-filtered down (the pixel integrates its footprint),
noise is added to the display values, and only then are they quantised to the file's bit depth.

Sources: the Poisson-Gaussian (shot + read) noise model of A. Foi et al., "Practical
Poissonian-Gaussian noise modeling and fitting for single-image raw-data", IEEE TIP 2008.
"""

from __future__ import annotations

import numpy as np

__all__ = ["box_downsample", "gaussian", "relative", "poisson_gaussian", "quantize", "add_noise", "NOISE_MODELS"]

NOISE_MODELS = ("gaussian", "relative", "poisson_gaussian")


def box_downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Average non-overlapping `factor` x `factor` blocks: (H k, W k, ...) -> (H, W, ...)."""
    k = int(factor)
    if k == 1:
        return image
    h, w = image.shape[0] // k, image.shape[1] // k
    if (h * k, w * k) != image.shape[:2]:
        raise ValueError(f"image shape {image.shape[:2]} is not a multiple of {k}")
    rest = image.shape[2:]
    blocks = image.reshape((h, k, w, k) + rest)
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(image.dtype)


def gaussian(image: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """image + N(0, sigma^2), independently per pixel and channel."""
    if sigma <= 0:
        return image
    return (image + rng.normal(0.0, sigma, image.shape)).astype(np.float32)


def relative(image: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """image (1 + N(0, sigma^2)): Gaussian noise whose std is `sigma` times the value ("1% noise" read
    as 1% of the signal), independently per pixel and channel. Dark pixels are nearly noiseless."""
    if sigma <= 0:
        return image
    return (image * (1.0 + rng.normal(0.0, sigma, image.shape))).astype(np.float32)


def poisson_gaussian(
    image: np.ndarray, photons_at_one: float, read_sigma: float, rng: np.random.Generator
) -> np.ndarray:
    """Shot noise plus read noise: ``Poisson(x * q) / q + N(0, read_sigma^2)`` with q the photon
    count of a value of 1 (`photons_at_one`); the variance is ``x / q + read_sigma^2``."""
    q = float(photons_at_one)
    x = np.clip(image, 0.0, None).astype(np.float64)
    shot = rng.poisson(x * q) / q if q > 0 else x
    return gaussian(shot.astype(np.float32), read_sigma, rng)


def add_noise(image: np.ndarray, sigma: float, rng: np.random.Generator, model: str = "gaussian") -> np.ndarray:
    """Noise of strength `sigma` (the standard deviation at a value of 1):

    - ``gaussian``: additive, std `sigma` everywhere;
    - ``relative``: multiplicative, std `sigma` times the value;
    - ``poisson_gaussian``: shot noise with std `sigma` at a value of 1 (q = 1 / sigma^2) plus
      read noise `sigma` / 4.
    """
    if sigma <= 0:
        return image.astype(np.float32)
    if model == "gaussian":
        return gaussian(image, sigma, rng)
    if model == "relative":
        return relative(image, sigma, rng)
    if model == "poisson_gaussian":
        return poisson_gaussian(image, 1.0 / sigma**2, sigma / 4.0, rng)
    raise ValueError(f"noise model must be one of {NOISE_MODELS}, got {model!r}")


def quantize(image: np.ndarray, bits: int) -> np.ndarray:
    """Round display values in [0, 1] to `bits`-bit codes and back (clipping outside [0, 1]):
    exactly what writing and reading an 8- or 16-bit file does. ``bits=0`` means float: no-op."""
    if not bits:
        return image.astype(np.float32)
    top = float(2**bits - 1)
    return (np.round(np.clip(image, 0.0, 1.0) * top) / top).astype(np.float32)
