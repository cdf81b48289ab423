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
from scipy.spatial import ConvexHull, QhullError

import jax.numpy as jnp

from ..io.atomic import write_cache_file
from ..lighting.environment import Environment
from ..lighting.visibility import DirectionCells, OcclusionSettings, Visibility, direction_cells
from .gbuffer import SHADOW_OFFSET_REL
from .raycast import BARYCENTRIC_SLACK, PARALLEL_EPS, any_hit_along

__all__ = ["hull_vertices", "may_be_occluded", "occluding_faces", "environment_visibility", "occluded_share",
           "shadow_offset", "probe_share", "cast_visibility"]

#: Bump when the rays change, so that cached tables of an older release are not read.
_CACHE_VERSION = "pbrfit-visibility/1"
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
