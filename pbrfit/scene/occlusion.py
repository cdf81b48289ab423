"""Environment visibility of points on the fixed mesh: one shadow ray per point and direction cell.

`environment_visibility` casts, from each point moved off its face along the geometric normal
(by ``SHADOW_OFFSET_REL * mesh.scale``, as the G-buffer's light rays), one ray along the centre
of each direction cell of `pbrfit.lighting.visibility.direction_cells` and packs whether it left
the mesh into `pbrfit.lighting.visibility.Visibility`'s bits. The rays of one cell are parallel,
so they are cast together (`pbrfit.scene.raycast.any_hit_along`, float64, no embree needed).
Two exact shortcuts spare most rays:

- a point whose tangent plane has no part of the mesh above it (no vertex of the mesh's convex
  hull higher than half the offset) can be hit by no ray leaving its face: every point of a
  convex mesh is one (`may_be_occluded`);
- a cell whose centre lies below a point's face is not cast for it: the integrators test the
  point's horizon per sample direction themselves (`pbrfit.lighting.visibility.visible`), and
  the cell's part above the horizon counts as open.

`blocked_hits` casts the blocked rays again for their closest hit, where the light a blocked
direction brings comes from (`pbrfit.lighting.visibility.Bounce`), and `observed_radiance_at`
reads that light from what the capture's pixels saw nearest to the hit.

`occluded_share` says how much of the environment's irradiance the mesh blocks at some points:
what ``occlusion="auto"`` decides with (`probe_share`), after `occluding_faces` found a face with
mesh above it at all (none on a convex mesh: no ray is cast). `cast_visibility` puts it together:
direction cells of the environment, the rays, a `Visibility`. The rays are cached on disk like
the G-buffers.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Optional

import numpy as np
import trimesh
from jaxtyping import Bool, Float
from scipy.spatial import ConvexHull, QhullError, cKDTree

import jax.numpy as jnp

from ..io.atomic import write_cache_file
from ..lighting.environment import Environment
from ..lighting.visibility import DirectionCells, OcclusionSettings, Visibility, direction_cells
from ..lighting.visibility import blocked_cells
from .gbuffer import SHADOW_OFFSET_REL
from .raycast import BARYCENTRIC_SLACK, PARALLEL_EPS, any_hit_along, cast, make_first_hit

__all__ = ["hull_vertices", "may_be_occluded", "occluding_faces", "environment_visibility", "occluded_share",
           "shadow_offset", "probe_share", "cast_visibility", "blocked_hits", "observed_radiance_at",
           "BOUNCE_NEIGHBOURS", "SAME_SURFACE_COS", "UNSEEN_SPACINGS"]

#: Bump when the rays change, so that cached tables of an older release are not read.
_CACHE_VERSION = "pbrfit-visibility/1"
#: Rays per call of the closest-hit caster in `blocked_hits` (bounds its (rays, 3) arrays).
_HIT_BLOCK = 1 << 20
#: Seen points averaged by `observed_radiance_at` (the images' noise falls as 1/sqrt of it; the
#: radiance is blurred over about that many pixels' footprints).
BOUNCE_NEIGHBOURS = 8
#: Least cosine between normals of points `observed_radiance_at` takes for the same surface (60°).
SAME_SURFACE_COS = 0.5
#: A hit whose nearest seen point is farther than this many times the seen points' median spacing
#: counts as on a surface no camera saw (`observed_radiance_at`; the report's "unseen_hits").
UNSEEN_SPACINGS = 4.0
#: Points per block of `may_be_occluded` (bounds its (points, hull vertices) array).
_HULL_BLOCK = 4096
#: A closed mesh whose volume is within this fraction of its convex hull's is taken as convex: a
#: UV sphere's quads, planar in exact arithmetic, are not quite so with float32 vertices (its hull
#: is 5e-9 larger); a dent this small blocks no light worth casting for.
CONVEX_VOLUME_REL = 1e-6


def shadow_offset(mesh: trimesh.Trimesh) -> float:
    """How far a shadow ray starts off its face: `SHADOW_OFFSET_REL` of the mesh's bounding-box diagonal."""
    return SHADOW_OFFSET_REL * float(mesh.scale)


def hull_vertices(mesh: trimesh.Trimesh) -> np.ndarray:
    """(H, 3) float64 vertices of the mesh's convex hull (all vertices where qhull cannot build
    one: a flat mesh): the highest point of the mesh above any plane is one of them."""
    vertices = np.asarray(mesh.vertices, np.float64)
    try:
        return vertices[ConvexHull(vertices).vertices]
    except (QhullError, ValueError):  # a flat or degenerate set: every vertex serves
        return vertices


def may_be_occluded(mesh: trimesh.Trimesh, points: Float[np.ndarray, "P 3"],
                    normals: Float[np.ndarray, "P 3"]) -> Bool[np.ndarray, "P"]:
    """Whether any part of the mesh rises above each point's tangent plane (geometric normal) by
    more than half the shadow offset: elsewhere no ray that leaves the face can hit the mesh."""
    hull = hull_vertices(mesh)
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    limit = 0.5 * shadow_offset(mesh)
    out = np.zeros(len(points), bool)
    for s in range(0, len(points), _HULL_BLOCK):
        p, n = points[s:s + _HULL_BLOCK], normals[s:s + _HULL_BLOCK]
        height = hull @ n.T - np.sum(p * n, -1)                          # (H, block)
        out[s:s + _HULL_BLOCK] = height.max(0) > limit
    return out


def occluding_faces(mesh: trimesh.Trimesh) -> Bool[np.ndarray, "F"]:
    """Faces with some of the mesh above their plane (by more than half the shadow offset), on
    the side a camera can see: the outside of a closed mesh (its winding, turned outward),
    either side of an open one. None on a convex mesh: a closed mesh whose volume is its convex
    hull's is answered without a test per face."""
    solid = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), process=True)  # seams merged
    tri = np.asarray(mesh.triangles, np.float64)
    closed = bool(solid.is_watertight) and bool(solid.is_winding_consistent)
    hull = hull_vertices(mesh)
    if closed:
        try:
            if ConvexHull(hull).volume <= abs(float(solid.volume)) * (1.0 + CONVEX_VOLUME_REL):
                return np.zeros(len(tri), bool)
        except (QhullError, ValueError):  # (flat: not closed after all)
            pass
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), np.finfo(np.float64).tiny)
    if closed and float(solid.volume) < 0:
        normal = -normal
    limit = 0.5 * shadow_offset(mesh)
    out = np.zeros(len(tri), bool)
    for s in range(0, len(tri), _HULL_BLOCK):
        height = hull @ normal[s:s + _HULL_BLOCK].T - np.sum(tri[s:s + _HULL_BLOCK, 0] * normal[s:s + _HULL_BLOCK], -1)
        out[s:s + _HULL_BLOCK] = height.max(0) > limit
        if not closed:
            out[s:s + _HULL_BLOCK] |= height.min(0) < -limit
    return out


def _cache_key(mesh, points, normals, directions) -> str:
    h = hashlib.sha256(_CACHE_VERSION.encode())
    h.update(repr((SHADOW_OFFSET_REL, PARALLEL_EPS, BARYCENTRIC_SLACK)).encode())
    for a in (mesh.vertices, mesh.faces, points, normals, directions):
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:32]


def environment_visibility(mesh: trimesh.Trimesh, points: Float[np.ndarray, "P 3"],
                           normals: Float[np.ndarray, "P 3"], directions: Float[np.ndarray, "K 3"],
                           cache_dir: Optional[os.PathLike] = None) -> np.ndarray:
    """(P, ceil(K / 8)) uint8 packed bits (little-endian within a byte, `numpy.packbits`): bit k
    of row p is 0 where the ray from point p (moved off its face along its geometric normal
    ``normals``, which faces the camera) along unit world direction k hits the mesh, 1 where it
    leaves it or where direction k lies below the face (module docstring). With ``cache_dir``
    the bits are read from / written to ``cache_dir/visibility-<hash>.npy``, the hash covering
    the mesh, the points, their normals and the directions."""
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    directions = np.asarray(directions, np.float64)
    shape = (len(points), (len(directions) + 7) // 8)
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"visibility-{_cache_key(mesh, points, normals, directions)}.npy"
        try:
            cached = np.load(path, allow_pickle=False)
            if cached.shape == shape and cached.dtype == np.uint8:
                return cached
        except (OSError, ValueError, EOFError):  # missing or damaged: recompute
            pass
    open_ = np.ones((len(points), len(directions)), bool)
    candidates = np.flatnonzero(may_be_occluded(mesh, points, normals))
    if len(candidates):
        tri = np.asarray(mesh.triangles, np.float64)
        start = points[candidates] + normals[candidates] * shadow_offset(mesh)
        facing = normals[candidates] @ directions.T > 0                  # (C, K)
        for k, d in enumerate(directions):
            rows = np.flatnonzero(facing[:, k])
            if len(rows):
                open_[candidates[rows], k] = ~any_hit_along(tri, start[rows], d)
    bits = np.packbits(open_, axis=1, bitorder="little")
    if path is not None:
        write_cache_file(path, lambda f: np.save(f, bits))
    return bits


def occluded_share(bits: np.ndarray, normals: Float[np.ndarray, "P 3"], directions: Float[np.ndarray, "K 3"],
                   power: Float[np.ndarray, " K"]) -> float:
    """The share of the irradiance the mesh blocks at the points (summed over them):
    Σ_p Σ_k (1 - V_pk) P_k (n_p·d_k)+ / Σ_p Σ_k P_k (n_p·d_k)+, with cells' powers P_k and
    centres d_k and the points' geometric normals n_p. 0 where no light arrives at all."""
    k = len(directions)
    open_ = np.unpackbits(bits, axis=1, count=k, bitorder="little").astype(np.float64)
    weight = np.maximum(np.asarray(normals, np.float64) @ np.asarray(directions, np.float64).T, 0.0) * power
    total = float(weight.sum())
    return float(((1.0 - open_) * weight).sum() / total) if total > 0 else 0.0


def probe_share(mesh: trimesh.Trimesh, env: Environment, points: Float[np.ndarray, "P 3"],
                normals: Float[np.ndarray, "P 3"], settings: OcclusionSettings = OcclusionSettings(),
                cache_dir: Optional[os.PathLike] = None) -> float:
    """`occluded_share` at ``settings.probe_points`` of the points, evenly spread over their order
    (call it where `occluding_faces` finds some: elsewhere the share is 0 without casting). Where
    the probe takes every point, its rays are cached in ``cache_dir`` as `cast_visibility`
    caches them, so the cast that follows reads them back instead of casting them again."""
    if not len(points):
        return 0.0
    pick = np.unique(np.linspace(0, len(points) - 1, min(len(points), settings.probe_points)).round().astype(np.int64))
    cells = direction_cells(env, settings)
    every = len(pick) == len(points)  # then the probe's rays are the cast's: cached for it
    bits = environment_visibility(mesh, np.asarray(points)[pick], np.asarray(normals)[pick], cells.directions,
                                  cache_dir if every else None)
    return occluded_share(bits, np.asarray(normals)[pick], cells.directions, cells.power)


def cast_visibility(mesh: trimesh.Trimesh, env: Environment, points: Float[np.ndarray, "P 3"],
                    normals: Float[np.ndarray, "P 3"], settings: OcclusionSettings = OcclusionSettings(),
                    cache_dir: Optional[os.PathLike] = None) -> tuple[Visibility, DirectionCells]:
    """The points' `Visibility` of ``env`` (and the direction cells it was cast on), the rays
    cached in ``cache_dir`` (`environment_visibility`). ``normals``: the points' geometric
    normals, facing the camera."""
    cells = direction_cells(env, settings)
    bits = environment_visibility(mesh, points, normals, cells.directions, cache_dir)
    return Visibility(jnp.asarray(cells.labels), jnp.asarray(bits),
                      jnp.asarray(np.asarray(normals, np.float32))), cells


def blocked_hits(mesh: trimesh.Trimesh, points: Float[np.ndarray, "P 3"], normals: Float[np.ndarray, "P 3"],
                 directions: Float[np.ndarray, "K 3"], bits: np.ndarray,
                 cache_dir: Optional[os.PathLike] = None) -> tuple[np.ndarray, np.ndarray]:
    """Where each blocked ray of ``bits`` (`environment_visibility`'s, for the same points, normals
    and directions) first hits the mesh, in the order of `pbrfit.lighting.visibility.blocked_cells`:
    (N, 3) float32 points and (N, 3) float32 unit normals of the faces hit, turned against the ray
    (the side it sees); NaN where the closest-hit caster (Embree where installed) finds no face for
    a ray the any-hit test found blocked (one grazing an edge). With ``cache_dir`` they are cached
    beside the bits."""
    rows, cells = blocked_cells(bits, len(directions))
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"bounce-hits-{_cache_key(mesh, points, normals, directions)}.npy"
        try:
            cached = np.load(path, allow_pickle=False)
            if cached.shape == (len(rows), 6) and cached.dtype == np.float32:
                return cached[:, :3], cached[:, 3:]
        except (OSError, ValueError, EOFError):  # missing or damaged: recompute
            pass
    out = np.full((len(rows), 6), np.nan, np.float32)
    if len(rows):
        points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
        directions = np.asarray(directions, np.float64)
        tri = np.asarray(mesh.triangles, np.float64)
        face_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        face_normal /= np.maximum(np.linalg.norm(face_normal, axis=-1, keepdims=True), np.finfo(np.float64).tiny)
        first_hit = make_first_hit(mesh, "auto")
        offset = shadow_offset(mesh)
        for s in range(0, len(rows), _HIT_BLOCK):
            r, k = rows[s:s + _HIT_BLOCK], cells[s:s + _HIT_BLOCK]
            origin, d = points[r] + normals[r] * offset, directions[k]
            face, t, _, _ = cast(first_hit, tri, origin, d)
            hit = face >= 0
            fn = face_normal[face[hit]]
            fn *= -np.sign(np.sum(fn * d[hit], -1, keepdims=True) + 1e-30)
            out[s:s + _HIT_BLOCK][hit] = np.concatenate([origin[hit] + t[hit, None] * d[hit], fn], -1)
    if path is not None:
        write_cache_file(path, lambda f: np.save(f, out))
    return out[:, :3], out[:, 3:]


def observed_radiance_at(seen: Float[np.ndarray, "R 3"], seen_normals: Float[np.ndarray, "R 3"],
                         radiance: Float[np.ndarray, "R 3"], at: Float[np.ndarray, "N 3"],
                         at_normals: Float[np.ndarray, "N 3"],
                         neighbours: int = BOUNCE_NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 radiance leaving the surface at points ``at`` (with normals ``at_normals``),
    read from ``radiance`` seen at points ``seen`` (a capture's pixels, normals ``seen_normals``):
    of the ``neighbours`` seen points nearest to each, those whose normals lie within 60° of its
    own (the same surface, not another one close by), their median per channel (a glint one
    camera saw does not spread), or the nearest one's radiance where none does; 0 where ``at`` is
    NaN (no hit). And (N,) bool: whether the nearest seen point is farther than `UNSEEN_SPACINGS`
    times the seen points' median spacing (a surface no camera saw, read from the nearest one
    that was)."""
    radiance_out = np.zeros((len(at), 3), np.float32)
    unseen = np.zeros(len(at), bool)
    rows = np.flatnonzero(np.all(np.isfinite(at), -1))
    if not len(rows) or not len(seen):
        return radiance_out, unseen
    seen = np.asarray(seen, np.float64)
    tree = cKDTree(seen)
    some = seen[:: max(1, len(seen) // 4096)]
    spacing = float(np.median(tree.query(some, k=2, workers=-1)[0][:, 1])) if len(seen) > 1 else np.inf
    k = min(int(neighbours), len(seen))
    seen_normals, radiance = np.asarray(seen_normals, np.float32), np.asarray(radiance, np.float32)
    for s in range(0, len(rows), _HIT_BLOCK):
        r = rows[s:s + _HIT_BLOCK]
        dist, idx = tree.query(np.asarray(at[r], np.float64), k=k, workers=-1)
        dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
        same = np.einsum("nkc,nc->nk", seen_normals[idx], np.asarray(at_normals[r], np.float32)) > SAME_SURFACE_COS
        take = np.where(same.any(-1, keepdims=True), same, np.arange(k) == 0)
        # the median of the m taken: those left out sorted last, the mean of the middle one or two
        values = np.sort(np.where(take[..., None], radiance[idx], np.inf), axis=1)
        m = take.sum(-1)
        lo = np.take_along_axis(values, ((m - 1) // 2)[:, None, None], 1)[:, 0]
        hi = np.take_along_axis(values, (m // 2)[:, None, None], 1)[:, 0]
        radiance_out[r] = 0.5 * (lo + hi)
        unseen[r] = dist[:, 0] > UNSEEN_SPACINGS * spacing
    return radiance_out, unseen
