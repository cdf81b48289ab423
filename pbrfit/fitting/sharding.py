"""Sharding a fit over several devices: pixels split, texels replicated.

The solver's work is per pixel: every step renders each pixel, takes its 3 × 5 Jacobian by
forward mode and scatters w_pk J_pᵀ r_p and w_pk² J_pᵀ J_p onto its texels
(`pbrfit.fitting.objective`, `pbrfit.fitting.normal_matrix`). The per-texel arrays (T × 5 values, their 5 × 5
blocks, the CG vectors) are small next to the per-pixel ones (P × 3 × 5 Jacobians, with P in the
millions for a real capture). So the scheme is data parallel over pixels:

- every per-pixel array of a `Problem` (the `Observations` fields, the (P, 4) texel `index`
  and `weight`, per-pixel IBL integrals, the stencil's cells and corner weights, which
  `pbrfit.fitting.stencil.with_stencil` makes again for the padded pixels) is split along its
  leading axis over a one-axis device mesh named ``"pixels"`` (`PartitionSpec("pixels")`);
- everything else (free mask, smoothness pairs, scalars, split-sum tables) is replicated.

Nothing in the solver changes: under `jax.jit`, XLA partitions the per-pixel work across
devices, and each texel-space `segment_sum` becomes a per-device partial sum followed by an
all-reduce, so every device holds the full (replicated) texel-space state of the
Levenberg-Marquardt loop and its conjugate gradients.

Padding. A mesh of n devices needs P to be a multiple of n (the rows, a multiple of n × the
samples per pixel, so that no pixel's samples straddle two devices). `pad_observations` appends
inert pixels: normal +z, view -z (so n·v = -1 < 0, where `pbrfit.render.shade.shade` returns exactly 0 for
the punctual lights and the split-sum environment alike, through a `jnp.where` whose forward-
mode tangent is exactly 0 too), lights of zero radiance along +x (n·l = 0, v·l = 0: no
singular half vector even in the branch `where` discards), uv 0, exposure 0, target 0 and
residual weight 0.
Every tone map and both colour spaces send radiance 0 to 0 (`pbrfit.physics.color.encode`; the
ACES Hill fit maps 0 slightly below 0 and clips), and every robust loss keeps r = 0 at 0, so a
padded pixel's residual and Jacobian are exactly zero: E(x), its gradient and the normal
blocks are unchanged. Padded pixels belong to no view: ``view_index = pixel = -1``.
`pad_layout` pads a `TexelLayout` to match with texel 0 and weight 0, so padded pixels add
nothing to texel sums (nor to `coverage_counts`) even where their Jacobian would not be 0.
Build layouts from the real observations and pad them; a layout computed from padded
observations would give the padded pixels bilinear weights at uv 0.

`take_pixels` makes a problem of some of the pixels the same way: their rows, padded with inert
pixels to a size the mesh divides, placed as the problem's arrays are. `take_texels` then keeps
only the texels those pixels read (and the prior's partners of the texels that move), so that the
per-texel work of a search over a few texels of a large map is that of the few.

Results that are per pixel (the solver's residuals and Jacobians) come back padded; their
first ``num_real`` rows are the real pixels, in the original order. With several samples per
pixel, ``num_real`` counts rows: the residuals (one per pixel) have ``num_real / samples`` real
rows, the Jacobians (one per sample) ``num_real``.

`shard_problem` places host or single-device arrays with `jax.device_put`, so it is for one
process driving all the mesh's devices (one host, several GPUs or CPU devices).
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Bool, Float, Int

from .observations import PIXEL_FIELDS, Observations, TexelLayout
from .objective import LeftOut, Problem, TexelGrid
from .stencil import with_stencil
from ..lighting.pixel_ibl import per_row

__all__ = ["PIXEL_AXIS", "PAD_NORMAL", "PAD_VIEW", "PAD_LIGHT", "padded_size", "pad_observations", "pad_pixel_rows",
           "pad_layout", "pixel_mesh", "pixel_sharding", "shard_problem", "mesh_size", "take_pixels", "moving_pixels",
           "halving_sizes", "take_texels", "texel_rows", "set_texel_rows", "texel_program"]

#: Name of the mesh axis the pixels are split over.
PIXEL_AXIS = "pixels"
#: Geometry of a padded pixel: n·v = -1 (nothing is shaded) and n·l = v·l = 0.
PAD_NORMAL = (0.0, 0.0, 1.0)
PAD_VIEW = (0.0, 0.0, -1.0)
PAD_LIGHT = (1.0, 0.0, 0.0)

#: Tangent frame of a padded pixel: a normal map tilts its normal within z > 0, so n·v stays < 0.
PAD_TANGENT = (1.0, 0.0, 0.0, 1.0)


def padded_size(count: int, multiple: int) -> int:
    """The smallest multiple of `multiple` that is at least `count`."""
    if multiple < 1:
        raise ValueError(f"multiple must be a positive integer, got {multiple!r}")
    return -(-int(count) // multiple) * multiple


def _append(a, extra: int, fill) -> np.ndarray:
    """`a` (on the host) with `extra` rows of `fill` (broadcast to a row) appended along axis 0."""
    a = np.asarray(a)
    pad = np.broadcast_to(np.asarray(fill, a.dtype), (extra,) + a.shape[1:])
    return np.concatenate([a, pad], axis=0)


def _padded_pixel_fields(obs: Observations, multiple: int) -> dict:
    """The per-pixel fields of `obs` padded on the host (empty when no padding is needed)."""
    extra = padded_size(obs.num_rows, multiple * obs.samples) - obs.num_rows
    return _inert_rows(obs, extra) if extra else {}


def _inert_rows(obs: Observations, extra: int) -> dict:
    """The per-pixel fields of `obs` on the host with `extra` rows of inert pixels appended."""
    fills = dict(normal=PAD_NORMAL, tangent=PAD_TANGENT, view=PAD_VIEW, light_l=PAD_LIGHT, light_radiance=0.0, uv=0.0, exposure=0.0,
                 target=0.0, residual_weight=0.0, view_index=-1, pixel=-1)
    return {name: _append(getattr(obs, name), extra, fills[name]) for name in PIXEL_FIELDS}


def _padded_texel_rows(index, weight, multiple: int) -> tuple[np.ndarray, np.ndarray]:
    extra = padded_size(index.shape[0], multiple) - index.shape[0]
    return _append(index, extra, 0), _append(weight, extra, 0.0)


def pad_observations(obs: Observations, multiple: int) -> tuple[Observations, int]:
    """Pad the pixel axis to a multiple of `multiple` with inert pixels (module docstring).

    Returns the padded observations and the number of real rows (the first rows; pixels × samples
    per pixel, padded to a multiple of `multiple` pixels). Padded
    pixels have zero residual and zero Jacobian in `pbrfit.fitting.objective.pixel_residuals` and
    `linearize` for every model, environment, tone map, colour space and loss.
    """
    padded = _padded_pixel_fields(obs, multiple)
    return dataclasses.replace(obs, **{k: jnp.asarray(v) for k, v in padded.items()}), obs.num_rows


def pad_pixel_rows(
    index: Int[Array, "P 4"], weight: Float[Array, "P 4"], multiple: int, samples: int = 1
) -> tuple[Int[Array, "Q 4"], Float[Array, "Q 4"]]:
    """Texel indices and weights padded like `pad_observations` (of observations with `samples`
    rows per pixel): texel 0 with weight 0."""
    index, weight = _padded_texel_rows(index, weight, multiple * samples)
    return jnp.asarray(index), jnp.asarray(weight)


def pad_layout(layout: TexelLayout, multiple: int, samples: int = 1) -> TexelLayout:
    """A `TexelLayout` padded to match `pad_observations(obs, multiple)` (`samples`: the
    observations' rows per pixel)."""
    index, weight = pad_pixel_rows(layout.index, layout.weight, multiple, samples)
    return TexelLayout(index, weight, layout.shape)


def pixel_mesh(devices: Optional[Sequence[jax.Device]] = None) -> Mesh:
    """A one-axis mesh named ``"pixels"`` over `devices` (default: all of `jax.devices()`)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("pixel_mesh needs at least one device")
    return Mesh(np.asarray(devices, dtype=object), (PIXEL_AXIS,))


def pixel_sharding(mesh: Mesh) -> NamedSharding:
    """Split the leading (pixel) axis over the mesh's ``"pixels"`` axis."""
    return NamedSharding(mesh, PartitionSpec(PIXEL_AXIS))


def _put(tree, sharding: NamedSharding):
    return jax.tree_util.tree_map(lambda a: jax.device_put(a, sharding) if eqx.is_array(a) else a, tree)


def _restenciled(problem: Problem, changed: Problem) -> Problem:
    """``changed`` (``problem`` with other pixels) with its own stencil where ``problem`` has one:
    the stencil's per-pixel tables follow the pixels (`pbrfit.fitting.stencil.with_stencil`)."""
    return changed if problem.stencil is None else with_stencil(changed)


def shard_problem(problem: Problem, mesh: Mesh) -> Problem:
    """`problem` with its pixels split over `mesh` and everything else replicated on it (its
    stencil made again for the padded pixels, `_restenciled`).

    The pixel axis is padded with inert pixels (`pad_observations`, `pad_pixel_rows`) to a
    multiple of the mesh's size along ``"pixels"``; the real pixels are the first
    ``problem.obs.num_pixels`` rows. The objective, its gradient, the normal blocks and hence
    the solution of `pbrfit.fitting.solvers.structured.StructuredLM` are those of `problem` (to float32 round-off:
    sums run in a different order).
    """
    n = int(mesh.shape[PIXEL_AXIS])
    rows = pixel_sharding(mesh)
    whole = NamedSharding(mesh, PartitionSpec())
    # Padding is done on the host and the padded arrays go straight to their shards.
    obs = problem.obs
    pixel_fields = {name: getattr(obs, name) for name in PIXEL_FIELDS}
    pixel_fields.update(_padded_pixel_fields(obs, n))
    obs = dataclasses.replace(obs, **{k: jax.device_put(v, rows) for k, v in pixel_fields.items()})
    index, weight = problem.index, problem.weight
    if padded_size(index.shape[0], n * obs.samples) != index.shape[0]:
        index, weight = _padded_texel_rows(index, weight, n * obs.samples)
    changes = dict(obs=obs, index=jax.device_put(index, rows), weight=jax.device_put(weight, rows))
    if per_row(problem.ibl):  # per-pixel integrals (or occlusion factors) go with their pixels (zero for padding)
        count = padded_size(problem.ibl.num_pixels, n * obs.samples)
        table = _append(problem.ibl.table, count - problem.ibl.num_pixels, 0.0)
        changes["ibl"] = dataclasses.replace(problem.ibl, table=jax.device_put(table, rows))
    changes["stencil"] = None  # made again below: its per-pixel tables are not copied to every device
    for field in dataclasses.fields(problem):
        if field.name not in changes and not field.metadata.get("static", False):
            changes[field.name] = _put(getattr(problem, field.name), whole)
    return _restenciled(problem, dataclasses.replace(problem, **changes))


def mesh_size(problem: Problem) -> int:
    """How many devices `problem`'s pixels are split over (1 where they are not split)."""
    sharding = getattr(problem.obs.target, "sharding", None)
    return int(sharding.mesh.shape[PIXEL_AXIS]) if isinstance(sharding, NamedSharding) else 1


def moving_pixels(moving: Bool[np.ndarray, " T"], index, weight, samples: int) -> Int[np.ndarray, " N"]:
    """The pixels some sample of which reads a texel of ``moving`` (with a weight above 0)."""
    reads = np.any(moving[np.asarray(index)] & (np.asarray(weight) > 0), axis=1)
    return np.flatnonzero(reads.reshape(-1, samples).any(axis=1))


def halving_sizes(total: int, count: int, devices: int) -> list[int]:
    """``total`` pixels, then 1/2, 1/4, ... of them (each a multiple of ``devices``) while ``count``
    pixels fit: the sizes a problem over some of its pixels takes (`take_pixels`), so that a few
    programs serve every choice of pixels."""
    sizes = [int(total)]
    while count <= (half := padded_size(-(-sizes[-1] // 2), devices)) < sizes[-1]:
        sizes.append(half)
    return sizes


def take_pixels(problem: Problem, pixels: Int[np.ndarray, " N"], size: int, residuals=None) -> Problem:
    """`problem` over some of its pixels: the rows of ``pixels`` (every sample of each, in their
    order), then inert pixels (`pad_observations`'s) up to ``size`` pixels, a multiple of
    `mesh_size`; each per-pixel array placed as `problem`'s is, the rest shared.

    Its objective is `problem`'s less the terms of the pixels left out, so where those read no
    texel that moves, a change of the objective is the same on both (what
    `pbrfit.fitting.stages.repair` searches over the pixels of the texels it moves). With
    ``residuals`` (`problem`'s (P, 3) pixel residuals where its texels stand) the pixels left out
    are kept as a `pbrfit.fitting.objective.LeftOut` term: their part of the objective, their
    number and their rounding floor, so that the objective is `problem`'s itself."""
    s, n = problem.samples, int(size)
    if n % mesh_size(problem) or n < len(pixels):
        raise ValueError(f"take_pixels: {n} pixels cannot hold {len(pixels)} over {mesh_size(problem)} devices")
    rows = (np.asarray(pixels, np.int64)[:, None] * s + np.arange(s)).reshape(-1)
    extra = n * s - rows.size
    place = lambda a, host: jax.device_put(host, a.sharding)
    obs = problem.obs
    taken = dataclasses.replace(obs, **{name: np.asarray(getattr(obs, name))[rows] for name in PIXEL_FIELDS})
    fields = {name: place(getattr(obs, name), host) for name, host in _inert_rows(taken, extra).items()}
    index, weight = (_append(np.asarray(a)[rows], extra, 0) for a in (problem.index, problem.weight))
    changes = dict(obs=dataclasses.replace(obs, **fields), index=place(problem.index, index),
                   weight=place(problem.weight, weight))
    if per_row(problem.ibl):
        table = _append(np.asarray(problem.ibl.table)[rows], extra, 0.0)
        changes["ibl"] = dataclasses.replace(problem.ibl, table=place(problem.ibl.table, table))
    if residuals is not None:
        out = np.ones(problem.num_pixels, bool)
        out[np.asarray(pixels, np.int64)] = False
        r = np.asarray(residuals, np.float64)[: problem.num_pixels][out]
        eps = float(np.finfo(np.float32).eps)
        target, w = (np.asarray(obs.pixel_rows(a), np.float64)[out] for a in (obs.target, obs.residual_weight))
        terms = (0.5 * np.sum(r * r), problem.num_pixels - n, 0.5 * np.sum((eps * w * target) ** 2))
        changes["left_out"] = LeftOut(*(place(problem.smooth, np.float32(v + problem.left(name))) for v, name in
                                        zip(terms, ("energy", "pixels", "floor"))))
    return _restenciled(problem, dataclasses.replace(problem, **changes))


def take_texels(problem: Problem, x: Optional[Float[np.ndarray, "T K"]] = None,
                size: Optional[int] = None) -> tuple[Problem, Int[np.ndarray, " N"]]:
    """(`problem` over the texels its pixels read and the prior's partners of its texels with a
    free channel (those that move), which texel of `problem` each of its texels is).

    Its texels are those, in their order, then padding texels up to ``size``, one of T, 1/2,
    1/4, ... of `problem`'s T (`halving_sizes`, so that a few programs serve every choice;
    default: the least that holds them and one padding texel, the sink): every index into the
    texels is renumbered (the rows' taps, the grid's cell tables, the prior's pairs, the
    stencil's neighbours and cells), a table entry that leads out of the texels kept leads to the
    sink, and the padding texels are free nowhere and read by no pixel with a weight. The pairs
    kept are those of positive weight with both ends kept, padded with pairs of the sink of
    weight 0 to twice the texels (a grid's pairs number under that; `problem`'s own number at
    T), so that the program's shapes follow ``size`` alone. Its pixels' residuals, the prior's
    terms of the texels that move and the Gauss-Newton blocks among the texels kept are
    `problem`'s at the texels taken (``texel_rows(x, texels)``; the padding's entry of ``texels``
    is T), so a search or a solve moves them as on `problem` (`pbrfit.fitting.stages.repair`,
    `pbrfit.fitting.runner.Runner.refit`), where per-texel work costs in proportion to the
    texels kept, not to the map. With ``x`` (`problem`'s texels) and a
    `LeftOut` term, the prior's energy at ``x`` of the pairs dropped is added to it, so that the
    objective is `problem`'s too. ``Problem.texels`` is dropped. Where every texel is kept:
    `problem` itself."""
    t = problem.num_texels
    moving = np.any(np.asarray(problem.free) > 0, axis=1)
    index = np.asarray(problem.index)
    pairs, pair_weight = np.asarray(problem.pairs), np.asarray(problem.pair_weight)
    live = pair_weight > 0
    ends = np.concatenate([pairs[live & moving[pairs[:, 0]], 1], pairs[live & moving[pairs[:, 1]], 0]])
    read = np.asarray(problem.weight).reshape(problem.num_pixels, -1).any(axis=1)
    kept = [index.reshape(problem.num_pixels, -1)[read].reshape(-1), ends, np.flatnonzero(moving)]
    if problem.stencil is not None:  # a pixel's stencil cell need not be one of its taps
        kept.append(np.asarray(problem.stencil.cell)[read])
    kept = np.unique(np.concatenate(kept)).astype(np.int64)
    if len(kept) == t:
        return problem, np.arange(t)
    least = halving_sizes(t, len(kept) + 1, 1)[-1]
    size = least if size is None else int(size)
    if size < least or size not in halving_sizes(t, least, 1):
        raise ValueError(f"take_texels: {size} texels cannot hold {len(kept)} and a sink as a halving size of {t}")
    sink = len(kept)
    new = np.full(t + 1, sink, np.int32)  # a texel's new index (T: the padding's)
    new[kept] = np.arange(len(kept), dtype=np.int32)
    place = lambda a, host: jax.device_put(host, a.sharding)
    table = lambda a: place(a, _append(new[np.asarray(a)[kept]], size - len(kept), sink))  # (T, N) of texels
    keep = live & (new[pairs[:, 0]] < sink) & (new[pairs[:, 1]] < sink)
    kept_pairs = int(np.sum(keep))
    e = max(_pair_count(problem, size), kept_pairs)
    pad_pairs = lambda a, fill: place(a, _append(np.asarray(a)[keep], e - kept_pairs, fill))
    changes = dict(index=place(problem.index, new[index]), texels=None,
                   free=place(problem.free, _append(np.asarray(problem.free)[kept], size - len(kept), 0.0)),
                   pairs=place(problem.pairs, _append(new[pairs[keep]], e - kept_pairs, sink)),
                   pair_weight=pad_pairs(problem.pair_weight, 0.0))
    if problem.grid is not None:
        changes["grid"] = TexelGrid(problem.grid.shape, table(problem.grid.corners), table(problem.grid.corner_of))
    if problem.stencil is not None:
        st = problem.stencil
        changes["stencil"] = dataclasses.replace(st, neighbours=table(st.neighbours), cell=place(
            st.cell, new[np.asarray(st.cell)]), pair_offsets=pad_pairs(st.pair_offsets, st.centre))
    if x is not None and problem.left_out is not None:
        # ½ Σ smooth_residuals² over the pairs dropped, on the host (an eager call compiles per shape)
        a, b = pairs[~keep, 0], pairs[~keep, 1]
        x, chan = np.asarray(x, np.float64), np.max(np.asarray(problem.free), axis=0)
        d = pair_weight[~keep, None] * chan * (x[a] - x[b])
        prior = 0.5 * float(problem.smooth) * float(np.sum(d * d))
        changes["left_out"] = dataclasses.replace(problem.left_out, energy=place(
            problem.left_out.energy, np.float32(float(problem.left_out.energy) + prior)))
    return dataclasses.replace(problem, **changes), np.concatenate([kept, np.full(size - len(kept), t)])


def texel_rows(a: Float[np.ndarray, "T K"], texels: Int[np.ndarray, " N"]) -> Float[np.ndarray, "N K"]:
    """The rows of ``a`` at ``texels`` (`take_texels`'s), a padding texel's (index T) row 0's."""
    a = np.asarray(a)
    return np.concatenate([a, a[:1]])[texels]


def set_texel_rows(a: Float[np.ndarray, "T K"], texels: Int[np.ndarray, " N"], part) -> Float[np.ndarray, "T K"]:
    """A copy of ``a`` with its rows at ``texels`` (`take_texels`'s) from ``part``'s (padding left out)."""
    a = np.array(a)
    real = texels < len(a)
    a[texels[real]] = np.asarray(part)[real]
    return a



def _pair_count(problem: Problem, size: int) -> int:
    """The pairs `take_texels` pads to at ``size`` texels (more where more are kept): twice the
    texels (a grid's pairs number under that), `problem`'s own number at its T."""
    return problem.pairs.shape[0] if size == problem.num_texels else 2 * size


def texel_program(problem: Problem, taken: Problem, key_of, has) -> tuple[int, tuple]:
    """(texels to take, the key ``key_of`` gives that problem) where ``taken`` is `problem` over
    its least texels (`take_texels`): of T, 1/2, 1/4, ... of `problem`'s T that hold ``taken``'s,
    the least whose program is compiled already (``has(key)``), else ``taken``'s own. The keys of
    the larger counts are read from stand-ins with their texel and pair shapes (broadcast zeros,
    not for running), built without taking them. A larger program costs a little more per
    evaluation, a compile seconds (`pbrfit demo`'s fit compiled 4 s more when each repair pass
    took its own count)."""
    k = problem.free.shape[1]
    for size in reversed(halving_sizes(problem.num_texels, taken.num_texels, 1)[:-1]):
        key = key_of(dataclasses.replace(taken, free=np.broadcast_to(np.float32(0), (size, k)),
                                         pairs=np.broadcast_to(np.int32(0), (_pair_count(problem, size), 2))))
        if has(key):
            return size, key
    return taken.num_texels, key_of(taken)
