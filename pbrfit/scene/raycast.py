"""Ray casting against a triangle mesh: first hits, refined in float64.

`make_first_hit` returns a function from rays to the first face each one hits, backed by embree
(trimesh's `RayMeshIntersector`, float32; ``backend="embree"``) or by a numpy bounding-box
hierarchy (float64, dependency-free; ``backend="numpy"``); ``"auto"`` takes embree when embreex
is installed. `cast` refines the reported hit on its face with the Möller-Trumbore test in
float64, so where both backends report the same face they give the same distance and
barycentrics; embree's float32 traversal may pick the neighbour across an edge, or miss or add
a ray that grazes a silhouette.

Source: T. Möller, B. Trumbore, "Fast, minimum storage ray-triangle intersection", Journal of
Graphics Tools 2(1), 1997.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh
from jaxtyping import Float, Int

__all__ = ["has_embree", "make_first_hit", "cast", "moller_trumbore", "PARALLEL_EPS", "BARYCENTRIC_SLACK", "NORM_FLOOR"]

# Ray/triangle determinant floor, relative to |e1||e2||d|: below it the ray runs parallel to
# the triangle's plane and the hit is treated as a miss (its distance is undefined).
PARALLEL_EPS = 1e-12
# Barycentric slack for the numpy intersector, so that rays through a shared edge are not lost
# between the two triangles by rounding.
BARYCENTRIC_SLACK = 1e-10
# numpy intersector: faces per bounding box, and rays-times-boxes per chunk (~25 MB per
# (chunk, 3) float64 array).
_NUMPY_BLOCK = 32
_NUMPY_CHUNK = 1 << 20
# Vectors shorter than this are treated as zero before normalising (unit-scale quantities).
NORM_FLOOR = 1e-20

has_embree: bool = bool(getattr(trimesh.ray, "has_embree", False))


def moller_trumbore(o, d, v0, e1, e2):
    """Ray/triangle distance and barycentrics (Möller & Trumbore 1997), broadcasting, float64.

    Returns (t, b1, b2, ok): the hit is o + t d = (1 - b1 - b2) v0 + b1 v1 + b2 v2, with
    e1 = v1 - v0, e2 = v2 - v0; ok is False where the ray is parallel to the plane.
    """
    pvec = np.cross(d, e2)
    det = np.sum(e1 * pvec, axis=-1)
    scale = np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1) * np.linalg.norm(d, axis=-1)
    ok = np.abs(det) > PARALLEL_EPS * scale
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = o - v0
    b1 = np.sum(tvec * pvec, axis=-1) * inv
    qvec = np.cross(tvec, e1)
    b2 = np.sum(d * qvec, axis=-1) * inv
    t = np.sum(e2 * qvec, axis=-1) * inv
    return t, b1, b2, ok


def _morton_order(points: Float[np.ndarray, "N 3"]) -> Int[np.ndarray, "N"]:
    """Indices sorting points along a Z-order (Morton) curve of 10 bits per axis."""
    lo, hi = points.min(0), points.max(0)
    q = ((points - lo) / np.maximum(hi - lo, NORM_FLOOR) * 1023).astype(np.uint64)
    code = np.zeros(len(points), dtype=np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def _numpy_first_hit(tri: Float[np.ndarray, "F 3 3"]) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """First-hit search in numpy, float64: a one-level bounding-box hierarchy, then Möller-Trumbore.

    Faces are sorted along a Morton curve and grouped in blocks of `_NUMPY_BLOCK`; a ray is
    tested against the faces of every block whose (slightly padded) box it crosses. Tens of
    times slower than embree, but float64 throughout and dependency-free.
    """
    order = _morton_order(tri.mean(1))
    n_blocks = -(-len(tri) // _NUMPY_BLOCK)
    members = np.full(n_blocks * _NUMPY_BLOCK, -1, dtype=np.int64)
    members[: len(order)] = order
    members = members.reshape(n_blocks, _NUMPY_BLOCK)
    corners = tri[np.maximum(members, 0)].reshape(n_blocks, -1, 3)  # padding repeats face order[0]
    pad = 1e-9 * float(np.linalg.norm(tri.max((0, 1)) - tri.min((0, 1)))) + NORM_FLOOR
    lo, hi = corners.min(1) - pad, corners.max(1) + pad
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]

    def first_hit(origins, directions):
        out = np.full(len(origins), -1, dtype=np.int64)
        step = max(1, _NUMPY_CHUNK // n_blocks)
        for s in range(0, len(origins), step):
            o, d = origins[s : s + step], directions[s : s + step]
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / d[:, None, :]
                t1, t2 = (lo[None] - o[:, None]) * inv, (hi[None] - o[:, None]) * inv
                t_in = np.nanmax(np.fmin(t1, t2), axis=-1)  # NaN (ray on a slab plane) keeps the box
                t_out = np.nanmin(np.fmax(t1, t2), axis=-1)
            ray, block = np.nonzero(~((t_in > t_out) | (t_out < 0)))
            ray = np.repeat(ray, _NUMPY_BLOCK)
            face = members[block].ravel()
            ray, face = ray[face >= 0], face[face >= 0]
            t, b1, b2, ok = moller_trumbore(o[ray], d[ray], v0[face], e1[face], e2[face])
            slack = -BARYCENTRIC_SLACK
            valid = ok & (b1 >= slack) & (b2 >= slack) & (b1 + b2 <= 1 - slack) & (t > 0)
            ray, face, t = ray[valid], face[valid], t[valid]
            best = np.full(len(o), np.inf)
            np.minimum.at(best, ray, t)
            win = t == best[ray]
            out[s + ray[win]] = face[win]
        return out

    return first_hit


def make_first_hit(mesh: trimesh.Trimesh, backend: str):
    """A function (origins (N,3), unit directions (N,3)) -> first face hit per ray, -1 if none."""
    if backend == "auto":
        backend = "embree" if has_embree else "numpy"
    if backend == "embree":
        if not has_embree:
            raise RuntimeError("gbuffer: backend 'embree' requested but embreex is not installed")
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # here: needs the optional embreex

        intersector = RayMeshIntersector(mesh)
        return lambda o, d: np.asarray(intersector.intersects_first(o, d), dtype=np.int64)
    if backend == "numpy":
        tri = np.asarray(mesh.triangles, dtype=np.float64)
        return _numpy_first_hit(tri)
    raise ValueError(f"gbuffer: unknown backend {backend!r} (expected 'auto', 'embree' or 'numpy')")


def cast(first_hit, tri, origins, directions):
    """First hits refined in float64 on the reported face: (face, t, b1, b2), face -1 for misses."""
    face = first_hit(origins, directions)
    t = np.full(len(origins), np.inf)
    b1 = np.zeros(len(origins))
    b2 = np.zeros(len(origins))
    idx = np.nonzero(face >= 0)[0]
    f = face[idx]
    v0 = tri[f, 0]
    th, b1h, b2h, ok = moller_trumbore(origins[idx], directions[idx], v0, tri[f, 1] - v0, tri[f, 2] - v0)
    ok &= th > 0
    face[idx[~ok]] = -1
    t[idx[ok]], b1[idx[ok]], b2[idx[ok]] = th[ok], b1h[ok], b2h[ok]
    return face, t, b1, b2
