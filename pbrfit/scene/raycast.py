"""Ray casting against a triangle mesh: first hits, refined in float64.

`make_first_hit` returns a function from rays to the first face each one hits, backed by embree
(trimesh's `RayMeshIntersector`, float32; ``backend="embree"``) or by a numpy bounding-box
hierarchy (float64, 20-40 times slower; ``backend="numpy"``, the reference); ``"auto"`` takes embree
when embreex, a dependency, is installed. `cast` refines the reported hit on its face with the Möller-Trumbore test in
float64, so where both backends report the same face they give the same distance and
barycentrics; embree's float32 traversal may pick the neighbour across an edge, or miss or add
a ray that grazes a silhouette.

`any_hit_along` answers a different question, fast and in float64 without embree: which of many
rays that share one direction (shadow rays towards a distant light) hit anything at all.

Source: T. Möller, B. Trumbore, "Fast, minimum storage ray-triangle intersection", Journal of
Graphics Tools 2(1), 1997.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh
from jaxtyping import Float, Int

__all__ = ["has_embree", "resolved_backend", "make_first_hit", "cast", "moller_trumbore", "any_hit_along", "normalize",
           "any_perpendicular", "PARALLEL_EPS",
           "BARYCENTRIC_SLACK", "NORM_FLOOR"]

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
# `any_hit_along`: origins per pass, origins per cell of its grid on average, (origin, triangle)
# pairs tested at once (~40 MB per float64 (pairs, 3) array), and the most cells along a side.
_PARALLEL_CHUNK = 1 << 16
_PARALLEL_CELL_POINTS = 4
_PARALLEL_PAIRS = 1 << 21
_PARALLEL_MAX_CELLS = 1024

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


def resolved_backend(backend: str) -> str:
    """The intersector ``backend`` names: "auto" is "embree" where embreex is installed, else "numpy"."""
    if backend == "auto":
        return "embree" if has_embree else "numpy"
    return backend


def make_first_hit(mesh: trimesh.Trimesh, backend: str):
    """A function (origins (N,3), unit directions (N,3)) -> first face hit per ray, -1 if none."""
    backend = resolved_backend(backend)
    if backend == "embree":
        if not has_embree:
            raise RuntimeError("gbuffer: backend 'embree' requested but embreex is not installed")
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # here: embreex loads with it

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


def normalize(x: Float[np.ndarray, "*b 3"]) -> Float[np.ndarray, "*b 3"]:
    """``x`` / |x| along the last axis; 0 where |x| is below `NORM_FLOOR`."""
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(n > NORM_FLOOR, x / np.maximum(n, NORM_FLOOR), 0.0)


def any_perpendicular(n: Float[np.ndarray, "*b 3"]) -> Float[np.ndarray, "*b 3"]:
    """A unit vector perpendicular to each unit `n` (crossed with its least-aligned axis)."""
    axis = np.zeros_like(n)
    k = np.argmin(np.abs(n), axis=-1)
    np.put_along_axis(axis, k[..., None], 1.0, axis=-1)
    return normalize(np.cross(n, axis))


def _ranges(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For counts c_i: (i repeated c_i times, 0 .. c_i - 1 for each i), concatenated."""
    owner = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, local


def any_hit_along(tri: Float[np.ndarray, "F 3 3"], origins: Float[np.ndarray, "N 3"],
                  direction: Float[np.ndarray, "3"]) -> np.ndarray:
    """(N,) bool: whether the ray from each origin along the one ``direction`` hits a triangle at
    a distance > 0 (float64).

    The rays are parallel, so triangles and origins are projected once onto the plane
    perpendicular to the direction; the origins are binned on a uniform grid there, and each
    triangle is tested only against the origins in the cells its projected bounding box
    covers: inside the projected triangle (barycentrics with `BARYCENTRIC_SLACK`) and behind
    it (the triangle's depth along the direction at that point beyond the origin's). That is
    Möller-Trumbore's test for these rays; a triangle seen edge-on (determinant below
    `PARALLEL_EPS` relative) is missed, as there. Cost: about one test per origin and triangle
    that overlap in projection, instead of a traversal per ray.
    """
    tri = np.asarray(tri, np.float64)
    origins = np.asarray(origins, np.float64)
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    e1 = any_perpendicular(d)
    basis = np.stack([e1, np.cross(d, e1)])
    tri2, trid = tri @ basis.T, tri @ d                                # (F, 3, 2), (F, 3)
    a, b = tri2[:, 1] - tri2[:, 0], tri2[:, 2] - tri2[:, 0]
    det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    scale = np.linalg.norm(tri[:, 1] - tri[:, 0], axis=-1) * np.linalg.norm(tri[:, 2] - tri[:, 0], axis=-1)
    usable = np.abs(det) > PARALLEL_EPS * scale
    inv = np.where(usable, 1.0 / np.where(usable, det, 1.0), 0.0)
    # per triangle, one row: corner 0, the map from (x - corner 0) to (b1, b2), the depth's plane
    params = np.stack([tri2[:, 0, 0], tri2[:, 0, 1], b[:, 1] * inv, -b[:, 0] * inv, -a[:, 1] * inv, a[:, 0] * inv,
                       trid[:, 0], trid[:, 1] - trid[:, 0], trid[:, 2] - trid[:, 0]])   # (9, F)
    tlo, thi, tfar = tri2.min(1), tri2.max(1), trid.max(1)
    out = np.zeros(len(origins), bool)
    slack = -BARYCENTRIC_SLACK
    for s in range(0, len(origins), _PARALLEL_CHUNK):
        o = origins[s:s + _PARALLEL_CHUNK]
        o2, od = o @ basis.T, o @ d
        lo, hi = o2.min(0), o2.max(0)
        keep = np.flatnonzero(usable & np.all(thi >= lo, 1) & np.all(tlo <= hi, 1) & (tfar > od.min()))
        if not len(keep):
            continue
        extent = np.maximum(hi - lo, NORM_FLOOR)
        size = max(np.sqrt(extent[0] * extent[1] * _PARALLEL_CELL_POINTS / len(o)),
                   float(extent.max()) / _PARALLEL_MAX_CELLS)
        cells = np.clip(np.ceil(extent / size).astype(np.int64), 1, _PARALLEL_MAX_CELLS)
        to_cell = lambda x: np.floor(np.clip((x - lo) / size, 0, cells - 1)).astype(np.int64)  # noqa: E731
        oc = to_cell(o2)
        cell = oc[:, 1] * cells[0] + oc[:, 0]
        order = np.argsort(cell, kind="stable")
        points = np.stack([o2[:, 0], o2[:, 1], od])[:, order]           # (3, N) origins in cell order
        counts = np.bincount(cell, minlength=int(cells[0] * cells[1]))
        first = np.cumsum(counts) - counts
        nearest = np.full(len(counts), np.inf)                          # each cell's least origin depth
        np.minimum.at(nearest, cell, od)
        c0, c1 = to_cell(tlo[keep]), to_cell(thi[keep])
        span = c1 - c0 + 1
        owner, local = _ranges(span[:, 0] * span[:, 1])
        tc = (c0[owner, 1] + local // span[owner, 0]) * cells[0] + c0[owner, 0] + local % span[owner, 0]
        tri_of = keep[owner]
        inside = np.where(tfar[tri_of] > nearest[tc], counts[tc], 0)  # a triangle behind a cell's origins hits none
        tri_of, tc, inside = tri_of[inside > 0], tc[inside > 0], inside[inside > 0]
        # (origin, triangle) pairs, a batch of (triangle, cell) entries at a time
        bounds = np.searchsorted(np.cumsum(inside), np.arange(_PARALLEL_PAIRS, int(inside.sum()), _PARALLEL_PAIRS))
        for lo_e, hi_e in zip(np.r_[0, bounds], np.r_[bounds, len(tc)]):
            owner, local = _ranges(inside[lo_e:hi_e])
            t = params[:, tri_of[lo_e:hi_e][owner]]
            k = first[tc[lo_e:hi_e]][owner] + local
            x = points[:, k]
            qx, qy = x[0] - t[0], x[1] - t[1]
            b1 = qx * t[2] + qy * t[3]
            b2 = qx * t[4] + qy * t[5]
            hit = (b1 >= slack) & (b2 >= slack) & (b1 + b2 <= 1 - slack) & (t[6] + b1 * t[7] + b2 * t[8] > x[2])
            out[s + order[k[hit]]] = True
    return out
