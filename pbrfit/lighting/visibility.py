"""Environment visibility of fixed geometry: which directions of the environment reach a point.

A point on a mesh sees the environment only where no other part of the mesh is in the way:

    L_o = ∫ f(l, v) L_env(l) V(p, l) (n·l) dω,

V(p, l) = 1 where the ray from p along l leaves the mesh, 0 where it hits it (and where l lies
below the face p is on: light from behind the surface). Geometry never moves in a fit, so V is
computed once, outside JAX (`pbrfit.scene.occlusion`), and the integrators read it.

A shadow ray per sample direction would be exact, but the per-pixel integrals draw
2 + levels directions per sample step (about 10,000 a pixel at the default 512 steps and 17
levels) and the Monte Carlo reference 2 per step: hundreds of millions of rays for a capture.
Instead V is tabulated per point on *direction cells*, a partition of the environment's texels
(`direction_cells`): a coarse grid of ``OcclusionSettings.rows`` × 2 rows cells, each split in
four while it carries more than ``power_share`` of the environment's power (luminance × solid
angle), down to single texels. A sun gets one cell per texel, an even sky cells of
180° / rows. One shadow ray per point and cell, along the cell's centre, stands for the cell;
an integrator reads V(p, l) from the cell of the texel l falls in, times the point's own
horizon test (geometric normal · l > 0), which is exact. The error is that of a shadow edge
drawn at the cell's size: a texel for bright light, 180° / rows for the rest
(`experiments/occlusion.py` measures it).

Light bounced off the mesh (`Bounce`): a blocked direction is not dark. It carries the radiance
leaving the surface the ray hits, toward the point. Geometry never moves, so where each blocked
ray lands is cast once too (`pbrfit.scene.occlusion.blocked_hits`), and the radiance there is
read from the capture itself: the median linear radiance of the pixels that saw the surface
nearest to the hit (`pbrfit.scene.occlusion.observed_radiance_at`). The captured images serve
as the radiance cache of Nimier-David et al., "Material and Lighting Reconstruction for Complex
Indoor Scenes with Texture-space Differentiable Rendering" (EGSR 2021), read once instead of
refreshed: what a camera saw holds every bounce of the real scene, and needs no material. The
error is the hit surface's view dependence (its radiance toward the cameras stands for its
radiance toward the point) and, where no camera saw the hit, the nearest seen surface standing
for it. The integrators read V(p, l) L_env(l) + (1 - V(p, l)) L_bounce(p, cell(l))
(`incoming`), still times the point's horizon test.

The split sum has no per-sample directions to mask; it takes per-point factors instead
(`split_sum_factors`): the share of the irradiance that arrives (diffuse) and the share of the
specular lobe's environment light that arrives, on a few roughness levels (specular).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, UInt8

from ..physics import brdf
from ..physics.color import luminance
from .settings import BOUNCE_MODES, OCCLUSION_MODES
from .environment import Environment, direction_to_uv, dot3, from_environment_frame, texel_directions, texel_solid_angles

__all__ = ["OCCLUSION_MODES", "OcclusionSettings", "DirectionCells", "direction_cells", "Visibility", "Bounce",
           "blocked_cells", "visibility_rows", "visible", "incoming", "SPECULAR_LEVELS", "split_sum_factors", "factors_at"]

#: Roughness levels of the split sum's specular factor (`split_sum_factors`), r_j = j / (levels - 1).
SPECULAR_LEVELS = 5


@dataclasses.dataclass(frozen=True)
class OcclusionSettings:
    """Knobs of environment occlusion (module docstring); defaults from `experiments/occlusion.py`.

    Attributes:
        rows: rows of the coarse cell grid (2 × rows columns): the shadow edge's resolution
            for light that is not bright (16: 11.25°).
        power_share: a cell carrying more than this share of the environment's power is split
            in four, down to single texels.
        auto_share: with ``occlusion="auto"``, occlusion is on when the mesh blocks at least
            this share of the irradiance (luminance-weighted, cosine-weighted) at the probed
            points.
        probe_points: how many points ``"auto"`` probes (evenly spread over the rows).
        bounce: whether the per-pixel integrals' blocked directions bring the radiance the
            capture shows on the surface they hit (`Bounce`; the split sum's factors take none):
            "on", "off" (dark, as in a render of direct light only) or "auto" (`BOUNCE_MODES`):
            the fit runs both ways from integrals of the same samples and keeps the one of lower
            residual σ.
    """

    rows: int = 16
    power_share: float = 1.0 / 256.0
    auto_share: float = 0.01
    probe_points: int = 1024
    bounce: str = "auto"

    def __post_init__(self):
        if not (isinstance(self.rows, (int, np.integer)) and 1 <= self.rows <= 1024):
            raise ValueError(f"OcclusionSettings.rows must be an integer from 1 to 1024, got {self.rows!r}")
        for name in ("power_share", "auto_share"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 < value <= 1.0):
                raise ValueError(f"OcclusionSettings.{name} must be a number in (0, 1], got {value!r}")
        if not (isinstance(self.probe_points, (int, np.integer)) and self.probe_points >= 1):
            raise ValueError(f"OcclusionSettings.probe_points must be an integer >= 1, got {self.probe_points!r}")
        if self.bounce not in BOUNCE_MODES:
            raise ValueError(f"OcclusionSettings.bounce must be one of {', '.join(BOUNCE_MODES)}, got {self.bounce!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class DirectionCells:
    """A partition of an environment's texels into direction cells (numpy; `direction_cells`).

    Attributes:
        labels: (H, W) int32 cell of each texel.
        directions: (K, 3) float64 unit world direction of each cell's centre (solid-angle
            weighted mean of its texels' directions).
        power: (K,) float64 the cell's luminance × solid angle.
        radius: (K,) float64 angular radius of the cell, sqrt(Ω / π) for its solid angle Ω.
    """

    labels: np.ndarray
    directions: np.ndarray
    power: np.ndarray
    radius: np.ndarray

    @property
    def count(self) -> int:
        return int(self.directions.shape[0])


def _splits(lo: int, hi: int, parts: int) -> list[int]:
    """Boundaries of ``parts`` near-equal ranges of [lo, hi) (fewer when the range is shorter)."""
    return sorted(set(np.linspace(lo, hi, min(parts, hi - lo) + 1).round().astype(int).tolist()))


def direction_cells(env: Environment, settings: OcclusionSettings = OcclusionSettings()) -> DirectionCells:
    """The direction cells of ``env`` (module docstring): a rows × 2 rows grid over its texels,
    each cell split at its middle row and column while it holds more than ``power_share`` of the
    power and more than one texel."""
    radiance = np.asarray(env.radiance, np.float64)
    h, w, _ = radiance.shape
    omega = np.broadcast_to(texel_solid_angles(h, w), (h, w))
    power = np.asarray(luminance(radiance), np.float64) * omega
    limit = settings.power_share * max(float(power.sum()), np.finfo(np.float64).tiny)
    cum = np.pad(power.cumsum(0).cumsum(1), ((1, 0), (1, 0)))  # summed-area table

    def total(i0, i1, j0, j1):
        return cum[i1, j1] - cum[i0, j1] - cum[i1, j0] + cum[i0, j0]

    rows, cols = _splits(0, h, settings.rows), _splits(0, w, 2 * settings.rows)
    stack = [(i0, i1, j0, j1) for i0, i1 in zip(rows[:-1], rows[1:]) for j0, j1 in zip(cols[:-1], cols[1:])]
    cells = []
    while stack:
        i0, i1, j0, j1 = stack.pop()
        if total(i0, i1, j0, j1) > limit and (i1 - i0) * (j1 - j0) > 1:
            im, jm = (i0 + i1 + 1) // 2 if i1 - i0 > 1 else i1, (j0 + j1 + 1) // 2 if j1 - j0 > 1 else j1
            stack += [c for c in ((i0, im, j0, jm), (i0, im, jm, j1), (im, i1, j0, jm), (im, i1, jm, j1))
                      if c[0] < c[1] and c[2] < c[3]]
        else:
            cells.append((i0, i1, j0, j1))
    cells.sort()
    labels = np.zeros((h, w), np.int32)
    dirs = texel_directions(h, w)
    centre = np.zeros((len(cells), 3))
    cell_power = np.zeros(len(cells))
    cell_omega = np.zeros(len(cells))
    for k, (i0, i1, j0, j1) in enumerate(cells):
        labels[i0:i1, j0:j1] = k
        o = omega[i0:i1, j0:j1, None]
        centre[k] = np.sum(dirs[i0:i1, j0:j1] * o, axis=(0, 1))
        cell_power[k] = total(i0, i1, j0, j1)
        cell_omega[k] = float(o.sum())
    centre /= np.maximum(np.linalg.norm(centre, axis=-1, keepdims=True), np.finfo(np.float64).tiny)
    world = np.asarray(from_environment_frame(jnp.asarray(centre), env.world_up, env.rotation_deg), np.float64)
    world /= np.linalg.norm(world, axis=-1, keepdims=True)
    return DirectionCells(labels, world, cell_power, np.sqrt(cell_omega / math.pi))


class Visibility(eqx.Module):
    """Which direction cells each point sees (`pbrfit.scene.occlusion.environment_visibility`).

    Attributes:
        labels: (H, W) cell of each environment texel (`DirectionCells.labels`); the
            environment the integrators read must have this size.
        bits: (P, ceil(K / 8)) uint8: bit k (little-endian within a byte) of row p is 1 where
            the ray from point p along cell k's centre leaves the mesh.
        normal: (P, 3) the points' geometric normals (world), facing the camera: directions
            below them are blocked by the point's own face.
        bounce: (P, K, 3) radiance arriving along each blocked cell (`Bounce`, dense for a few
            rows: `visibility_rows`), or None: blocked cells are dark.
    """

    labels: Int[Array, "H W"]
    bits: UInt8[Array, "P B"]
    normal: Float[Array, "P 3"]
    bounce: Optional[Float[Array, "P K 3"]] = None

    @property
    def num_points(self) -> int:
        return int(self.bits.shape[0])


@dataclasses.dataclass(frozen=True, eq=False)
class Bounce:
    """Radiance arriving at the points along their blocked direction cells (module docstring), one
    entry per zero bit of `Visibility.bits` (below K), row by row and cell by cell (numpy).

    Attributes:
        radiance: (N, 3) float32 linear radiance leaving the hit surface toward the point.
        offsets: (P + 1,) int64: row p's entries are radiance[offsets[p]:offsets[p + 1]].
    """

    radiance: np.ndarray
    offsets: np.ndarray


def blocked_cells(bits: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cells) of the zero bits of packed ``bits`` (P, ceil(K / 8)) below ``count`` = K, in
    row-major order: the order of `Bounce`'s entries."""
    open_ = np.unpackbits(np.asarray(bits), axis=1, count=count, bitorder="little")
    return np.nonzero(open_ == 0)


def visibility_rows(vis: Visibility, start: int, stop: int, pad: int = 0,
                    bounce: Optional[Bounce] = None) -> Visibility:
    """Rows [start, stop) of ``vis``, with ``pad`` rows of a visible-everywhere, +z-facing point
    added; with ``bounce`` (the whole of ``vis``'s) its entries of those rows as a dense (rows, K,
    3) `Visibility.bounce`."""
    bits, normal = vis.bits[start:stop], vis.normal[start:stop]
    dense = None
    if bounce is not None:
        count = int(np.max(np.asarray(vis.labels))) + 1
        dense = np.zeros((stop - start + pad, count, 3), np.float32)
        rows, cells = blocked_cells(np.asarray(bits), count)
        dense[rows, cells] = bounce.radiance[bounce.offsets[start]:bounce.offsets[stop]]
        dense = jnp.asarray(dense)
    if pad:
        bits = jnp.concatenate([bits, jnp.full((pad, bits.shape[1]), 255, bits.dtype)])
        normal = jnp.concatenate([normal, jnp.tile(jnp.asarray([[0.0, 0.0, 1.0]], normal.dtype), (pad, 1))])
    return Visibility(vis.labels, bits, normal, dense)


def _cell_lookup(vis: Visibility, l_world, d_env):
    """(bit, above, p, k) for directions of the points of ``vis``: the cell's bit (1: open), whether
    the direction is above the point's face, and the point and cell indices."""
    h, w = vis.labels.shape
    uv = direction_to_uv(d_env)
    i = jnp.clip(jnp.floor(uv[..., 1] * h).astype(jnp.int32), 0, h - 1)
    j = jnp.clip(jnp.floor(uv[..., 0] * w).astype(jnp.int32), 0, w - 1)
    k = vis.labels[i, j]
    p = jnp.arange(vis.bits.shape[0], dtype=jnp.int32).reshape((-1,) + (1,) * (k.ndim - 1 - _point_axis(k)))
    p = jnp.broadcast_to(p, k.shape)
    bit = (vis.bits[p, k >> 3] >> (k & 7).astype(jnp.uint8)) & jnp.uint8(1)
    ng = vis.normal.reshape(vis.normal.shape[:1] + (1,) * (k.ndim - 1 - _point_axis(k)) + (3,))
    above = dot3(jnp.broadcast_to(ng, l_world.shape).astype(l_world.dtype), l_world) > 0
    return bit, above, p, k


def visible(vis: Visibility, l_world: Float[Array, "*b P 3"], d_env: Float[Array, "*b P 3"]) -> Float[Array, "*b P"]:
    """V(p, l) for world directions ``l_world`` (and the same directions in the environment's
    frame, ``d_env``) of the points of ``vis``, whose axis is the second-to-last: 1 or 0."""
    bit, above, _, _ = _cell_lookup(vis, l_world, d_env)
    return jnp.where(above, bit.astype(l_world.dtype), 0.0)


def incoming(vis: Visibility, radiance: Float[Array, "*b P 3"], l_world: Float[Array, "*b P 3"],
             d_env: Float[Array, "*b P 3"]) -> Float[Array, "*b P C"]:
    """Radiance arriving at the points of ``vis`` along world directions ``l_world`` (``d_env`` in
    the environment's frame) whose environment radiance is ``radiance``, above the point's face
    (0 below it): V L_env (C = 3), and with ``vis.bounce`` the light of the blocked directions
    beside it, [V L_env, (1 - V) L_bounce] (C = 6; module docstring), so that integrals of the two
    come from the same samples."""
    bit, above, p, k = _cell_lookup(vis, l_world, d_env)
    open_ = bit.astype(radiance.dtype)[..., None]
    out = radiance * open_
    if vis.bounce is not None:
        out = jnp.concatenate([out, (1.0 - open_) * vis.bounce[p, k].astype(radiance.dtype)], -1)
    return jnp.where(above[..., None], out, 0.0)


def _point_axis(k) -> int:
    """Axis of the points in arrays of the integrators: (B, P) or (B, P, R): always axis 1, or 0 for (P,)."""
    return 0 if k.ndim == 1 else 1


# --- the split sum's factors ---------------------------------------------------------------------

#: Points per compiled call of `split_sum_factors` (bounds the (points, cells) arrays).
FACTOR_CHUNK = 4096


def split_sum_factors(vis: Visibility, cells: DirectionCells, n: Float[Array, "P 3"],
                      v: Float[Array, "P 3"]) -> np.ndarray:
    """(P, 1 + `SPECULAR_LEVELS`) float32 per point: [k_d, k_s(r_0), k_s(r_1), ...] at the levels
    r_j = j / (`SPECULAR_LEVELS` - 1), the shares of the environment light that arrive, summed
    over the direction cells (power P_k, centre d_k):

        k_d = Σ_k V_k P_k (n·d_k)+ / Σ_k P_k (n·d_k)+          (irradiance through the shading normal)
        k_s(r) = Σ_k V_k P_k w_k(r) / Σ_k P_k w_k(r),  w_k = exp(λ_k (R·d_k - 1)) (n·d_k)+

    with R the split sum's dominant direction at r (`pbrfit.lighting.ibl`) and w a spherical
    Gaussian for the GGX lobe (sharpness 1 / (2 α²) in the reflected direction, Wang et al.,
    "All-Frequency Rendering of Dynamic, Spatially-Varying Reflectance", 2009) widened by the cell
    (sharpness 1 / ρ_k² for angular radius ρ_k; the sharpnesses combine as λ_a λ_b / (λ_a + λ_b)).
    A share is 1 where no light arrives unoccluded either. V_k includes the point's horizon.
    ``cells`` are those ``vis`` was cast on; n, v the points' shading normals and view directions."""
    n, v = np.asarray(n, np.float32), np.asarray(v, np.float32)
    args = [jnp.asarray(a, jnp.float32) for a in (cells.directions, cells.power / max(cells.power.max(), 1e-30),
                                                   cells.radius)]
    levels = np.maximum(np.linspace(0.0, 1.0, SPECULAR_LEVELS), brdf.MIN_ROUGHNESS)
    args.append(jnp.asarray(brdf.alpha_from_roughness(jnp.asarray(levels, jnp.float32))))
    out = []
    total = n.shape[0]
    for start in range(0, total, FACTOR_CHUNK):
        stop = min(start + FACTOR_CHUNK, total)
        pad = FACTOR_CHUNK - (stop - start) if total > FACTOR_CHUNK else 0
        rows = visibility_rows(vis, start, stop, pad)
        grow = lambda a: np.concatenate([a[start:stop], np.tile(np.float32([[0, 0, 1]]), (pad, 1))])  # noqa: E731
        out.append(np.asarray(_factors(rows, *args, jnp.asarray(grow(n)), jnp.asarray(grow(v))))[: stop - start])
    return np.concatenate(out) if out else np.zeros((0, 1 + SPECULAR_LEVELS), np.float32)


@jax.jit
def _factors(vis, directions, power, radius, alphas, n, v):
    k = directions.shape[0]
    idx = jnp.arange(k, dtype=jnp.int32)
    bits = ((vis.bits[:, idx >> 3] >> (idx & 7).astype(jnp.uint8)) & 1).astype(n.dtype)   # (P, K)
    vk = bits * (vis.normal @ directions.T > 0)
    cos = jnp.maximum(n @ directions.T, 0.0)                                              # (P, K)
    share = lambda wgt: jnp.where(jnp.sum(wgt, -1) > 0,  # noqa: E731
                                  jnp.sum(wgt * vk, -1) / jnp.where(jnp.sum(wgt, -1) > 0, jnp.sum(wgt, -1), 1.0), 1.0)
    out = [share(power * cos)]
    nv = dot3(n, v)
    refl = 2 * nv[:, None] * n - v
    cell_sharp = 1.0 / (radius * radius)  # (a cell has a solid angle > 0)
    for j in range(SPECULAR_LEVELS):
        alpha = alphas[j]
        dom = brdf.safe_normalize(refl + (n - refl) * alpha)
        lobe = 1.0 / (2.0 * alpha * alpha)
        sharp = lobe * cell_sharp / (lobe + cell_sharp)                                   # (K,)
        wgt = power * jnp.exp(sharp * (dom @ directions.T - 1.0)) * cos
        out.append(share(wgt))
    return jnp.stack(out, -1)


def factors_at(factors: Float[Array, "P S"], roughness: Float[Array, " P"]) -> tuple:
    """(k_d (P, 1), k_s (P, 1)) of `split_sum_factors` at each point's roughness (linear in r)."""
    x = jnp.clip(roughness, 0.0, 1.0) * (SPECULAR_LEVELS - 1)
    i = jnp.clip(jnp.floor(x), 0, SPECULAR_LEVELS - 2).astype(jnp.int32)
    t = x - i
    spec = factors[:, 1:]
    lo = jnp.take_along_axis(spec, i[:, None], 1)
    hi = jnp.take_along_axis(spec, i[:, None] + 1, 1)
    return factors[:, 0:1], lo + (hi - lo) * t[:, None]
