"""Environment maps: loading, orientation, bilinear lookup, solid-angle-aware resampling and mips.

An environment is an equirectangular (latitude-longitude) image of linear radiance. Orientation
follows the capture format (`shared/spec/capture-format.md`): in the environment's own frame
(+y up) the top row looks along +y, the image centre looks along -z and u grows with the azimuth
``atan2(x, -z)``:

    u = 0.5 + atan2(x, -z) / (2 pi),        v = acos(y) / pi.

A world with ``world_up = "+z"`` is first mapped ``(x, y, z) -> (x, z, -y)`` (Blender to glTF), and
``rotation_deg`` turns the environment about the up axis, counter-clockwise seen from above: a world
direction d reads the image at ``R_up(-rotation) d``. So with ``+z`` up the image centre looks along
+y; Blender's own equirectangular world texture (centre along +x, ``u = 0.5 - atan2(y, x) / 2 pi``)
is this mapping with ``rotation_deg = -90``.

Images follow the in-memory convention (float32, (H, W, C), row 0 at the top); texel (i, j) has its
centre at ``u = (j + 0.5) / W``, ``v = (i + 0.5) / H``. Lookups are bilinear, wrap around in
azimuth (seamless at u = 0 = 1) and clamp at the poles.
"""

from __future__ import annotations

import functools
import math
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..errors import CaptureError
from ..io.images import color_channels, read_image
from ..physics.clamps import clamp_inward

__all__ = [
    "Environment",
    "EnvironmentWarning",
    "WORLD_UPS",
    "load_environment",
    "environment_lookup",
    "to_environment_frame",
    "from_environment_frame",
    "direction_to_uv",
    "uv_to_direction",
    "sample_equirect",
    "texel_directions",
    "texel_solid_angles",
    "resample_equirect",
    "mip_pyramid",
    "stack_levels",
    "sample_stack",
    "procedural_sky",
    "dot3",
]

#: World up axes the capture format allows.
WORLD_UPS = ("+y", "+z")

#: Environment files already warned of in this process (`EnvironmentWarning`): a fit reads its
#: environment more than once.
_WARNED: set = set()


class EnvironmentWarning(UserWarning):
    """An environment map read as the spec says, though it does not look like one: not 2:1, as
    a cube cross (4:3) or a mirror-ball probe (1:1) is, and an equirectangular image is."""


#: Squared length of a direction's horizontal part (x, z) below which the azimuth is undefined
#: (a pole): u is set to 0.5 there and atan2's gradient, infinite at the origin, is not taken.
POLE_EPS = 1e-12


class Environment(eqx.Module):
    """An equirectangular environment of linear radiance, with its orientation in the world.

    Attributes:
        radiance: (H, W, 3) linear radiance (already multiplied by the capture's intensity):
            float32 as `load_environment` gives it; an array given directly is kept as given.
        world_up: ``"+y"`` or ``"+z"``, the world axis the top row looks along.
        rotation_deg: turn about the up axis, degrees, counter-clockwise seen from above.
    """

    radiance: Float[Array, "H W 3"]
    world_up: str = eqx.field(static=True, default="+y")
    rotation_deg: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        if self.world_up not in WORLD_UPS:
            raise ValueError(f"Environment.world_up must be one of {WORLD_UPS}, got {self.world_up!r}")
        if self.radiance.ndim != 3 or self.radiance.shape[-1] != 3:
            raise ValueError(f"Environment.radiance must be (H, W, 3), got {self.radiance.shape}")


def load_environment(path, world_up: str = "+y", intensity: float = 1.0,
                     rotation_deg: float = 0.0, where: str = "environment") -> Environment:
    """Read an equirectangular HDR (EXR, HDR, ...) through OpenImageIO.

    One channel is replicated to RGB; channels past the third (alpha) are dropped. The image is
    the display window: an OpenEXR whose data window is smaller holds 0 outside it (OpenEXR's
    meaning), and overscan past the display window is cut. Negative
    values are clamped to 0 (radiance is not negative). Raises `CaptureError` naming the file when
    it cannot be read, is not an image, or holds NaN or inf pixels (an unreadable file's error is
    prefixed with ``where``: the capture's key or the option that gave it); warns (`EnvironmentWarning`,
    once per file) when it is not 2:1.
    """

    path = Path(path)
    if world_up not in WORLD_UPS:
        raise CaptureError(f"{path}: world_up must be one of {', '.join(WORLD_UPS)}, got {world_up!r}")
    real = lambda x: isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))  # noqa: E731
    if not (real(intensity) and math.isfinite(intensity) and intensity >= 0):
        raise CaptureError(f"{path}: environment intensity must be a finite number >= 0, got {intensity!r}")
    if not (real(rotation_deg) and math.isfinite(rotation_deg)):
        raise CaptureError(f"{path}: environment rotation_deg must be a finite number, got {rotation_deg!r}")
    if not path.is_file():
        raise CaptureError(f"{path}: environment file not found")
    pixels, info = read_image(path, where)  # a cropped OpenEXR is placed in its display window
    height, width = pixels.shape[:2]
    if abs(width - 2 * height) > 1 and str(path) not in _WARNED:  # odd sizes round either way

        _WARNED.add(str(path))
        warnings.warn(f"{path}: environment is {width} x {height}, not 2:1; read as an equirectangular "
                      "(lat-long) map all the same, as the capture spec says (a cube cross or a mirror-ball "
                      "probe would light the scene wrongly)", EnvironmentWarning, stacklevel=2)
    if pixels.shape[-1] == 2:
        raise CaptureError(f"{path}: environment has 2 channels; expected 1, 3 or 4")
    # R, G, B by name (one layer of a layered OpenEXR) or a grey Y, else the first three
    pixels = pixels[..., color_channels(info, "environment")]
    if pixels.shape[-1] == 1:
        pixels = np.repeat(pixels, 3, axis=-1)
    bad = ~np.isfinite(pixels)
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad.any(-1))[0])
        raise CaptureError(
            f"{path}: {int(bad.any(-1).sum())} environment pixels with NaN or inf values (first at row {row}, column {col})"
        )
    pixels = np.maximum(pixels, 0.0) * np.float32(float(intensity))
    return Environment(jnp.asarray(pixels, jnp.float32), world_up, float(rotation_deg))


def dot3(a: Float[Array, "*b 3"], b: Float[Array, "*b 3"]) -> Float[Array, "*b"]:
    """a·b over the last axis of length 3, written as three products.

    Not ``jnp.sum(a * b, -1)``: jaxlib 0.10.2's CPU backend rewrites that reduction into a dot
    that returns wrong values under ``jit`` once the arrays pass 2^15 elements and the result is
    multiplied back into an operand (jax-ml/jax#39103; XLA flag
    ``--xla_cpu_experimental_ynn_fusion_type=-reduce`` avoids it).
    """
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


# --- orientation -------------------------------------------------------------------------------

def to_environment_frame(dirs: Float[Array, "*b 3"], world_up: str = "+y",
                         rotation_deg: float = 0.0) -> Float[Array, "*b 3"]:
    """World directions -> the environment's own +y-up frame (axis change, then R_up(-rotation))."""
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    if world_up == "+z":
        x, y, z = x, z, -y
    if rotation_deg:
        c, s = math.cos(math.radians(-rotation_deg)), math.sin(math.radians(-rotation_deg))
        # Right-handed rotation about +y (counter-clockwise seen from above).
        x, z = c * x + s * z, -s * x + c * z
    return jnp.stack([x, y, z], axis=-1)


def from_environment_frame(dirs: Float[Array, "*b 3"], world_up: str = "+y",
                           rotation_deg: float = 0.0) -> Float[Array, "*b 3"]:
    """Inverse of `to_environment_frame`."""
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    if rotation_deg:
        c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
        x, z = c * x + s * z, -s * x + c * z
    if world_up == "+z":
        x, y, z = x, -z, y
    return jnp.stack([x, y, z], axis=-1)


def direction_to_uv(d: Float[Array, "*b 3"]) -> Float[Array, "*b 2"]:
    """Environment-frame unit direction -> equirect (u, v) in [0, 1]^2.

    ``u = 0.5 + atan2(x, -z) / 2pi``, ``v = atan2(sqrt(x^2 + z^2), y) / pi`` (= acos(y) / pi, but
    with a finite gradient at the poles). Double-``where`` keeps gradients finite at x = z = 0,
    the zero vector included (v = 0 there, as at the +y pole; arctan2(0, 0) has no gradient).
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    r2 = x * x + z * z
    ok = r2 > POLE_EPS
    xs, zs = jnp.where(ok, x, 1.0), jnp.where(ok, -z, 1.0)
    u = jnp.where(ok, 0.5 + jnp.arctan2(xs, zs) / (2 * math.pi), 0.5)
    s = jnp.sqrt(jnp.where(ok, r2, 1.0))
    v = jnp.where(ok, jnp.arctan2(s, y) / math.pi, jnp.where(y < 0.0, 1.0, 0.0))
    return jnp.stack([u, v], axis=-1)


def uv_to_direction(uv: Float[Array, "*b 2"]) -> Float[Array, "*b 3"]:
    """Inverse of `direction_to_uv`: (u, v) -> environment-frame unit direction."""
    phi = (uv[..., 0] - 0.5) * (2 * math.pi)
    theta = uv[..., 1] * math.pi
    st = jnp.sin(theta)
    return jnp.stack([st * jnp.sin(phi), jnp.cos(theta), -st * jnp.cos(phi)], axis=-1)


def texel_directions(height: int, width: int) -> np.ndarray:
    """(H, W, 3) float64 environment-frame directions of texel centres."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    theta, phi = np.meshgrid(v * np.pi, (u - 0.5) * 2 * np.pi, indexing="ij")
    st = np.sin(theta)
    return np.stack([st * np.sin(phi), np.cos(theta), -st * np.cos(phi)], axis=-1)


def texel_solid_angles(height: int, width: int) -> np.ndarray:
    """(H, 1) float64 exact solid angle of one texel per row: (2pi/W)(cos theta_top - cos theta_bottom)."""
    edges = np.cos(np.linspace(0.0, np.pi, height + 1))
    return ((edges[:-1] - edges[1:]) * (2 * np.pi / width))[:, None]


# --- lookup ------------------------------------------------------------------------------------

def _towards_poles(top, bot, y, fy, height, north, south):
    """Finish a bilinear read in v so that it reaches the poles.

    Texel centres stop half a row short of the poles, where every column meets. Between the
    first row's centres and the north pole (``y < 0``) the read goes linearly from that row's
    value (bilinear in u) to ``north``, the row's mean over u (likewise for the last row and
    ``south``). Clamping to the first row instead reads one azimuth of a ring half a row from
    the pole, tilted towards it: a first-order error in exactly the direction, straight up, that
    a floor's normal looks along (the irradiance there was 1.7% off under a 60° sun with the
    default 32-row map, 3.7% at 16 rows; now 0.1%).
    """
    above = (y < 0)[..., None]
    below = (y > height - 1)[..., None]
    top = jnp.where(above, north, top)
    bot = jnp.where(below, south, bot)
    fy = jnp.where(above, 2.0 * fy - 1.0, jnp.where(below, 2.0 * fy, fy))
    return top * (1 - fy) + bot * fy


def sample_equirect(image: Float[Array, "H W C"], uv: Float[Array, "*b 2"]) -> Float[Array, "*b C"]:
    """Bilinear sample of an equirect image at (u, v): wraps in u and, past the first and last
    rows' centres, runs to each pole's value, the mean of that row (`_towards_poles`).
    Continuous over the sphere and differentiable."""
    h, w, c = image.shape
    x = uv[..., 0] * w - 0.5
    y = uv[..., 1] * h - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)
    c0, c1 = jnp.mod(x0, w), jnp.mod(x0 + 1, w)
    r0, r1 = jnp.clip(y0, 0, h - 1), jnp.clip(y0 + 1, 0, h - 1)
    flat = image.reshape(h * w, c)
    g = lambda r, cc: flat[r * w + cc]
    top = g(r0, c0) * (1 - fx) + g(r0, c1) * fx
    bot = g(r1, c0) * (1 - fx) + g(r1, c1) * fx
    return _towards_poles(top, bot, y, fy, h, jnp.mean(image[0], 0), jnp.mean(image[-1], 0))


@jax.jit
def environment_lookup(env: Environment, dirs: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """Radiance arriving from world directions ``dirs`` (unit), bilinear in the full-resolution map."""
    d = to_environment_frame(dirs, env.world_up, env.rotation_deg)
    return sample_equirect(env.radiance, direction_to_uv(d))


# --- resampling and mips -----------------------------------------------------------------------

def _row_weights(h_src: int, h_dst: int) -> np.ndarray:
    """(h_dst, h_src) weights: solid-angle overlap of source rows with target rows, rows sum to 1."""
    a = np.linspace(0.0, np.pi, h_src + 1)
    b = np.linspace(0.0, np.pi, h_dst + 1)
    lo = np.maximum(b[:-1, None], a[None, :-1])
    hi = np.minimum(b[1:, None], a[None, 1:])
    wgt = np.where(hi > lo, np.cos(lo) - np.cos(np.maximum(hi, lo)), 0.0)
    return wgt / wgt.sum(1, keepdims=True)


def _col_weights(w_src: int, w_dst: int) -> np.ndarray:
    """(w_dst, w_src) weights: azimuth overlap of source columns with target columns, rows sum to 1."""
    a = np.linspace(0.0, 1.0, w_src + 1)
    b = np.linspace(0.0, 1.0, w_dst + 1)
    wgt = np.clip(np.minimum(b[1:, None], a[None, 1:]) - np.maximum(b[:-1, None], a[None, :-1]), 0, None)
    return wgt / wgt.sum(1, keepdims=True)


@functools.partial(jax.jit, static_argnames=("height", "width"))
def resample_equirect(image: Float[Array, "H W C"], height: int, width: int) -> Float[Array, "h w C"]:
    """Box-filter an equirect image to (height, width), weighting source texels by solid angle.

    Each target texel is the solid-angle average of the source radiance over its footprint, so the
    integral of radiance over the sphere (the irradiance a sun contributes, say) is preserved. Exact
    2x steps are done by reshaping; a remaining non-integer ratio by dense overlap matrices.
    """
    h, w, c = image.shape
    while h >= 2 * height and w >= 2 * width and h % 2 == 0 and w % 2 == 0:
        sa = jnp.asarray(texel_solid_angles(h, w)[:, 0].reshape(h // 2, 2), image.dtype)
        pairs = image.reshape(h // 2, 2, w // 2, 2, c)
        weights = sa / sa.sum(1, keepdims=True)
        image = jnp.einsum("ab,abjkc->ajc", weights, pairs, precision=jax.lax.Precision.HIGHEST) * 0.5
        h, w = h // 2, w // 2
    if (h, w) == (height, width):
        return image
    rows = jnp.asarray(_row_weights(h, height), image.dtype)
    cols = jnp.asarray(_col_weights(w, width), image.dtype)
    return jnp.einsum("ih,hwc,jw->ijc", rows, image, cols, precision=jax.lax.Precision.HIGHEST)


def mip_pyramid(image: Float[Array, "H W C"], min_height: int = 1) -> list:
    """Solid-angle-weighted mip chain: level k+1 halves level k (rounding up) until ``min_height``."""
    levels = [image]
    while levels[-1].shape[0] > min_height:
        h, w = levels[-1].shape[:2]
        levels.append(resample_equirect(levels[-1], max((h + 1) // 2, min_height), max((w + 1) // 2, 1)))
    return levels


def stack_levels(levels) -> tuple:
    """Pad a list of (h_k, w_k, C) levels into one (K, H0, W0, C) array; returns (stack, shapes).

    ``shapes`` is a tuple of (h_k, w_k), static, so a level index can be dynamic under ``jit``.
    """
    h0 = max(l.shape[0] for l in levels)
    w0 = max(l.shape[1] for l in levels)
    padded = [jnp.pad(l, ((0, h0 - l.shape[0]), (0, w0 - l.shape[1]), (0, 0))) for l in levels]
    return jnp.stack(padded), tuple((int(l.shape[0]), int(l.shape[1])) for l in levels)


def _pole_means(stack, shapes) -> Float[Array, "K 2 C"]:
    """Per level of a padded stack, the means of its first and last rows (its two pole values)."""
    return jnp.stack([jnp.stack([jnp.mean(stack[k, 0, :w], 0), jnp.mean(stack[k, h - 1, :w], 0)])
                      for k, (h, w) in enumerate(shapes)])


def _sample_level(stack, shapes, uv, level, poles):
    """Bilinear sample of integer level ``level`` (int array) of a padded stack (as `sample_equirect`)."""
    k, h0, w0, c = stack.shape
    hs = jnp.asarray([s[0] for s in shapes], jnp.int32)[level]
    ws = jnp.asarray([s[1] for s in shapes], jnp.int32)[level]
    x = uv[..., 0] * ws - 0.5
    y = uv[..., 1] * hs - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
    c0, c1 = jnp.mod(x0, ws), jnp.mod(x0 + 1, ws)
    r0, r1 = jnp.clip(y0, 0, hs - 1), jnp.clip(y0 + 1, 0, hs - 1)
    flat = stack.reshape(k * h0 * w0, c)
    base = level * (h0 * w0)
    g = lambda r, cc: flat[base + r * w0 + cc]
    top = g(r0, c0) * (1 - fx) + g(r0, c1) * fx
    bot = g(r1, c0) * (1 - fx) + g(r1, c1) * fx
    return _towards_poles(top, bot, y, fy, hs, poles[level, 0], poles[level, 1])


def sample_stack(stack: Float[Array, "K H W C"], shapes: tuple, uv: Float[Array, "*b 2"],
                 level: Float[Array, "*b"]) -> Float[Array, "*b C"]:
    """Trilinear sample of a padded level stack at continuous ``level`` (clamped to [0, K-1]).

    Linear in the stack's values and piecewise linear in ``level``, so differentiable w.r.t. both;
    at level 0 and K-1 (roughness 0 and 1) with the derivative from inside (`pbrfit.physics.clamps.clamp_inward`:
    a clip's is half of it there).
    """

    k = stack.shape[0]
    level = clamp_inward(level, 0.0, k - 1.0)
    l0 = jnp.clip(jnp.floor(level), 0, max(k - 2, 0)).astype(jnp.int32)
    t = (level - l0)[..., None]
    poles = _pole_means(stack, shapes)
    a = _sample_level(stack, shapes, uv, l0, poles)
    if k == 1:
        return a
    b = _sample_level(stack, shapes, uv, l0 + 1, poles)
    return a * (1 - t) + b * t


# --- a procedural sky --------------------------------------------------------------------------

def procedural_sky(height: int = 128, width: int | None = None, sun_elevation_deg: float = 35.0,
                   sun_azimuth_deg: float = 40.0, sun_radius_deg: float = 2.0,
                   sun_illuminance: float = 8.0, zenith=(0.18, 0.32, 0.75), horizon=(0.75, 0.82, 0.95),
                   ground=(0.25, 0.21, 0.17), world_up: str = "+y") -> Environment:
    """A sky with a sun disk, a glow around it and a darker ground, as an `Environment`.

    Directions are in the environment frame (+y up). The sun disk has uniform radiance
    ``sun_illuminance / (pi r^2)`` (r its angular radius, radians), so it delivers about
    ``sun_illuminance`` at normal incidence; azimuth 0 looks along -z, growing towards +x.
    Sky radiance blends horizon to zenith colour with elevation; the ground is constant and meets
    the sky in a soft band a few degrees wide. Not physically calibrated: a test scene with the
    dynamic range and the sharp feature (the sun) that real outdoor light has.
    """
    width = 2 * height if width is None else width
    d = texel_directions(height, width)
    y = d[..., 1:2]
    el, az = math.radians(sun_elevation_deg), math.radians(sun_azimuth_deg)
    sun = np.array([math.cos(el) * math.sin(az), math.sin(el), -math.cos(el) * math.cos(az)])
    t = np.clip(y, 0, 1) ** 0.5
    sky = (1 - t) * np.asarray(horizon) + t * np.asarray(zenith)
    blend = np.clip(0.5 + y / math.radians(6.0), 0, 1)
    rad = blend * sky + (1 - blend) * np.asarray(ground)
    ang = np.arccos(np.clip(d @ sun, -1, 1))[..., None]
    r = math.radians(sun_radius_deg)
    disk = np.clip((r - ang) / (0.25 * r) + 0.5, 0, 1)          # anti-aliased edge, ~r/4 wide
    rad = rad + disk * sun_illuminance / (math.pi * r * r) * np.array([1.0, 0.95, 0.85])
    rad = rad + 0.6 * np.exp(-ang / math.radians(8.0)) * np.array([1.0, 0.9, 0.7]) * (y > -0.05)
    return Environment(jnp.asarray(rad, jnp.float32), world_up, 0.0)
