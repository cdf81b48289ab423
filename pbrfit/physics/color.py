"""Color: the sRGB transfer function, exposure, and tone mapping operators.

All functions are elementwise, differentiable ``jnp`` functions of linear RGB (..., 3) arrays
(the sRGB curve is per channel; tone maps that mix channels say so). Their clamps are
`pbrfit.physics.clamps.clamp_inward`: a pixel whose radiance is exactly 0 (a metal's black channel) or
exactly at a clip keeps the derivative from inside, not half of it.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .clamps import clamp_inward

__all__ = [
    "TONEMAPS",
    "COLOR_SPACES",
    "srgb_to_linear",
    "linear_to_srgb",
    "srgb_to_linear_host",
    "linear_to_srgb_host",
    "apply_exposure",
    "tonemap_reinhard",
    "tonemap_aces_narkowicz",
    "tonemap_aces_hill",
    "tonemap_khronos_neutral",
    "tonemap",
    "inverse_tonemap",
    "encode",
    "luminance",
]

TONEMAPS = ("none", "reinhard", "aces_narkowicz", "aces_hill", "khronos_neutral")
COLOR_SPACES = ("linear", "srgb")

# IEC 61966-2-1 sRGB constants.
_SRGB_LINEAR_CUTOFF = 0.0031308
_SRGB_ENCODED_CUTOFF = 0.04045
#: Floor inside the sRGB power so neither branch of `jnp.where` has an infinite derivative
#: (x^(1/2.4) at 0) or a NaN (negative base); values below the cutoff take the linear branch.
_POW_FLOOR = 1e-8


def _decode(x, xp):
    """sRGB decode with the array module `xp` (`jax.numpy` or `numpy`), keeping x's float dtype."""
    hi = xp.power((xp.maximum(x, _SRGB_ENCODED_CUTOFF) + 0.055) / 1.055, 2.4)
    return xp.where(x <= _SRGB_ENCODED_CUTOFF, x / 12.92, hi)


def _encode(x, xp):
    """sRGB encode with the array module `xp` (`jax.numpy` or `numpy`), keeping x's float dtype."""
    hi = 1.055 * xp.power(xp.maximum(x, _SRGB_LINEAR_CUTOFF), 1.0 / 2.4) - 0.055
    return xp.where(x <= _SRGB_LINEAR_CUTOFF, 12.92 * x, hi)


@jax.jit  # one fused kernel when called eagerly (output encoding, decoding frames)
def srgb_to_linear(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Decode sRGB to linear (IEC 61966-2-1): x / 12.92 below 0.04045, else ((x + 0.055)/1.055)^2.4."""
    return _decode(jnp.asarray(x), jnp)


@jax.jit
def linear_to_srgb(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Encode linear to sRGB (IEC 61966-2-1): 12.92 x below 0.0031308, else 1.055 x^(1/2.4) - 0.055."""
    return _encode(jnp.asarray(x), jnp)


def srgb_to_linear_host(x) -> np.ndarray:
    """`srgb_to_linear` in numpy (float32), for host work on files (decoding frames, writing
    PNGs): no XLA kernel compiled per image shape, no device round trip."""
    return np.asarray(_decode(np.asarray(x, np.float32), np), np.float32)


def linear_to_srgb_host(x) -> np.ndarray:
    """`linear_to_srgb` in numpy (float32), for host work on files (see `srgb_to_linear_host`)."""
    return np.asarray(_encode(np.asarray(x, np.float32), np), np.float32)


def apply_exposure(x: Float[ArrayLike, "..."], ev) -> Float[Array, "..."]:
    """Scale radiance by 2^ev (exposure value in stops)."""
    return jnp.asarray(x) * jnp.exp2(jnp.asarray(ev, dtype=jnp.result_type(x, float)))


def luminance(x: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    """Rec. 709 / sRGB relative luminance Y = 0.2126 R + 0.7152 G + 0.0722 B."""
    x = jnp.asarray(x)
    return 0.2126 * x[..., 0] + 0.7152 * x[..., 1] + 0.0722 * x[..., 2]


def tonemap_reinhard(x):
    """Reinhard et al. 2002, per channel: x / (1 + x)."""
    x = clamp_inward(x, 0.0)
    return x / (1.0 + x)


#: Input cap of the ACES fits: from here up both give 1 in every channel (their rational parts
#: exceed 1 and are clipped), and the cap keeps x² and the derivatives' x³ inside float32
#: (uncapped, the gradient was NaN from about 1e18 and the value from 1e20).
ACES_INPUT_MAX = 1e9


def tonemap_aces_narkowicz(x):
    """K. Narkowicz 2015, "ACES Filmic Tone Mapping Curve" (fit of the ACES RRT+ODT, per channel):
    clamp(x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14), 0, 1). The input is used as is (no 0.6
    pre-scale), matching the glTF Sample Viewer's ``toneMapACES_Narkowicz``.
    """
    x = clamp_inward(x, 0.0, ACES_INPUT_MAX)
    return clamp_inward(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


# S. Hill's ACES fit (BakingLab ACES.hlsl), as in the glTF Sample Viewer: sRGB -> ACES AP1
# (with the RRT saturation), the RRT+ODT rational fit, then back to linear sRGB. Row-major
# matrices applied as M @ rgb.
_ACES_INPUT = jnp.array(
    [[0.59719, 0.35458, 0.04823], [0.07600, 0.90834, 0.01566], [0.02840, 0.13383, 0.83777]]
)
_ACES_OUTPUT = jnp.array(
    [[1.60475, -0.53108, -0.07367], [-0.10208, 1.10813, -0.00605], [-0.00327, -0.07276, 1.07602]]
)


def tonemap_aces_hill(x):
    """S. Hill's ACES fit (glTF Sample Viewer ``toneMapACES_Hill``); mixes channels.

    c = M_in rgb; c = (c (c + 0.0245786) - 0.000090537) / (c (0.983729 c + 0.4329510) + 0.238081);
    out = clamp(M_out c, 0, 1). Without the viewer's optional /0.6 exposure boost.
    """
    x = clamp_inward(x, 0.0, ACES_INPUT_MAX)
    c = jnp.einsum("ij,...j->...i", _ACES_INPUT.astype(x.dtype), x, precision=jax.lax.Precision.HIGHEST)
    c = (c * (c + 0.0245786) - 0.000090537) / (c * (0.983729 * c + 0.4329510) + 0.238081)
    out = jnp.einsum("ij,...j->...i", _ACES_OUTPUT.astype(x.dtype), c, precision=jax.lax.Precision.HIGHEST)
    return clamp_inward(out, 0.0, 1.0)


def tonemap_khronos_neutral(x):
    """Khronos PBR Neutral tone mapper (Khronos 3D Commerce, 2024); mixes channels.

    x -= offset where offset = m - 6.25 m^2 if m = min(x) < 0.08 else 0.04; if max(x) < 0.76
    return x; else compress the peak p = max(x) to 1 - (1 - 0.76)^2 / (p + 1 - 2 * 0.76) and
    desaturate towards it by g = 1 - 1 / (0.15 (p - p_new) + 1).
    """
    start = 0.8 - 0.04
    desaturation = 0.15
    x = clamp_inward(x, 0.0)
    low = jnp.min(x, axis=-1, keepdims=True)
    offset = jnp.where(low < 0.08, low - 6.25 * low * low, 0.04)
    x = x - offset
    peak = jnp.max(x, axis=-1, keepdims=True)
    d = 1.0 - start
    safe_peak = jnp.maximum(peak, start)  # the compressed branch is only taken above `start`
    new_peak = 1.0 - d * d / (safe_peak + d - start)
    compressed = x * (new_peak / safe_peak)
    g = 1.0 - 1.0 / (desaturation * (safe_peak - new_peak) + 1.0)
    compressed = compressed * (1.0 - g) + new_peak * g
    return jnp.where(peak < start, x, compressed)


_TONEMAPS = {
    "none": lambda x: jnp.asarray(x),
    "reinhard": tonemap_reinhard,
    "aces_narkowicz": tonemap_aces_narkowicz,
    "aces_hill": tonemap_aces_hill,
    "khronos_neutral": tonemap_khronos_neutral,
}


@functools.partial(jax.jit, static_argnames="name")
def tonemap(x: Float[ArrayLike, "... 3"], name: str) -> Float[Array, "... 3"]:
    """Apply the named tone mapping operator (one of `TONEMAPS`)."""
    if name not in _TONEMAPS:
        raise ValueError(f"unknown tone map {name!r}; expected one of {', '.join(TONEMAPS)}")
    return _TONEMAPS[name](x)


#: Display values are capped below 1 before `inverse_tonemap`: the operators reach 1 only at
#: infinity (Reinhard, Khronos PBR Neutral) or clip there (the ACES fits).
_INVERSE_CAP = 1.0 - 1e-4


def _positive_root(a, b, c):
    """The non-negative root of a t² + b t + c = 0 for a < 0 <= c (the roots' product c/a <= 0)."""
    return (-b - jnp.sqrt(jnp.maximum(b * b - 4.0 * a * c, 0.0))) / (2.0 * a)


def _inverse_reinhard(y):
    """x = y / (1 - y)."""
    return y / (1.0 - y)


def _inverse_aces_narkowicz(y):
    """y (2.43 x² + 0.59 x + 0.14) = 2.51 x² + 0.03 x, solved for x >= 0 (a < 0 for y <= 1)."""
    return _positive_root(2.43 * y - 2.51, 0.59 * y - 0.03, 0.14 * y)


def _inverse_aces_hill(y):
    """c = M_out⁻¹ y; the rational fit solved per channel (a quadratic in c, a < 0 for c_out <= 1);
    x = M_in⁻¹ c."""
    hi = jax.lax.Precision.HIGHEST
    c = jnp.einsum("ij,...j->...i", jnp.linalg.inv(_ACES_OUTPUT).astype(y.dtype), y, precision=hi)
    c = _positive_root(0.983729 * c - 1.0, 0.4329510 * c - 0.0245786, 0.238081 * c + 0.000090537)
    return jnp.einsum("ij,...j->...i", jnp.linalg.inv(_ACES_INPUT).astype(y.dtype), c, precision=hi)


def _inverse_khronos_neutral(y):
    """Undo the peak compression (the compressed peak is max(y), so the peak p before it follows
    from p_new = 1 - d² / (p + d - start), and g from p), then the toe: with m the minimum after
    the offset, min(x) = sqrt(m / 6.25) where m < 0.04, else m + 0.04."""
    start, desaturation = 0.8 - 0.04, 0.15
    d = 1.0 - start
    new_peak = jnp.max(y, axis=-1, keepdims=True)
    safe_new = jnp.maximum(new_peak, start)
    peak = d * d / (1.0 - safe_new) - d + start
    g = 1.0 - 1.0 / (desaturation * (peak - safe_new) + 1.0)
    x = jnp.where(new_peak < start, y, (y - safe_new * g) / ((safe_new / peak) * (1.0 - g)))
    m = jnp.maximum(jnp.min(x, axis=-1, keepdims=True), 0.0)
    # the toe's inverse has infinite slope at m = 0: its gradient is taken as 0 there (double where)
    root = jnp.where(m > 0.0, jnp.sqrt(jnp.where(m > 0.0, m, 1.0) / 6.25), 0.0)
    low = jnp.where(m < 0.04, root, m + 0.04)
    return x + (low - m)


_INVERSE_TONEMAPS = {
    "none": lambda y: y,
    "reinhard": _inverse_reinhard,
    "aces_narkowicz": _inverse_aces_narkowicz,
    "aces_hill": _inverse_aces_hill,
    "khronos_neutral": _inverse_khronos_neutral,
}


@functools.partial(jax.jit, static_argnames="name")
def inverse_tonemap(y: Float[ArrayLike, "... 3"], name: str) -> Float[Array, "... 3"]:
    """The linear values that the named operator maps to `y` (tone-mapped, before any sRGB curve):
    exact where the operator is invertible, in closed form for each of `TONEMAPS`.

    With a tone map, display values are clipped to [0, 1 - 1e-4] first ("none" returns `y`), so a value at the top (where the ACES fits
    clip and the others reach only at infinity) comes back large but finite. Used to start fits
    of tone-mapped captures in linear radiance; the fits themselves compare through `encode`.
    """
    if name not in _INVERSE_TONEMAPS:
        raise ValueError(f"unknown tone map {name!r}; expected one of {', '.join(TONEMAPS)}")
    y = jnp.asarray(y)
    if name == "none":
        return y
    return jnp.maximum(_INVERSE_TONEMAPS[name](jnp.clip(y, 0.0, _INVERSE_CAP)), 0.0)


@functools.partial(jax.jit, static_argnames=("tonemap", "color_space"))
def encode(
    radiance: Float[ArrayLike, "... 3"], exposure_ev=0.0, tonemap: str = "none", color_space: str = "linear"
) -> Float[Array, "... 3"]:
    """Radiance -> the values an image file holds: × 2^ev, tone map, then the sRGB curve if asked.

    With tonemap "none" and color space "linear" this is only the exposure. For sRGB output the
    result is clipped to [0, 1] before encoding (an LDR file cannot hold more).
    """
    if color_space not in COLOR_SPACES:
        raise ValueError(f"unknown color space {color_space!r}; expected one of {', '.join(COLOR_SPACES)}")
    if tonemap not in _TONEMAPS:
        raise ValueError(f"unknown tone map {tonemap!r}; expected one of {', '.join(TONEMAPS)}")
    x = _TONEMAPS[tonemap](apply_exposure(radiance, exposure_ev))
    if color_space == "srgb":
        return linear_to_srgb(clamp_inward(x, 0.0, 1.0))
    return x
