"""Per-view geometry, computed once: camera rays, mesh hits, interpolated attributes, shadows.

Nothing here is differentiated. For every pixel of a view, a ray through the pixel centre is
intersected with the mesh; the hit gives the surface point, its face, its barycentric
coordinates and from them the interpolated shading normal, uv and tangent frame. One shadow ray
per light then says whether the light reaches the point. The result is a `GBuffer` of numpy
arrays, cached on disk by a hash of everything it depends on, and the latest ones in the process
(`MEMO_BYTES`, read-only).

Conventions pinned here (tests in ``tests/test_gbuffer.py``):

- Cameras (`pbrfit.scene.camera`) are OpenGL-style: camera-to-world 4x4, the camera looks down its -Z
  axis, +Y up, +X right. Pixel (i, j) (row i from the top, column j) has its centre at
  x = j + 0.5, y = i + 0.5; its camera-space ray is ((x - cx)/fx, -(y - cy)/fy, -1).
- Facing: surfaces are two-sided. Where the camera sees the back of a face (the face's
  geometric normal, from its winding, points away from the camera), the geometric normal, the
  shading normal, the tangent's xyz *and* its handedness w are all negated, as the
  glTF-Sample-Viewer does for back faces. So ``geometric_normal . view >= 0`` everywhere, and
  the bitangent ``cross(normal, tangent.xyz) * tangent.w`` is negated too (the whole TBN frame
  is mirrored). On a closed, consistently wound mesh nothing is ever flipped. The shading normal
  itself is *not* forced towards the camera (at silhouettes of smooth meshes it may face away
  by a few degrees; shading clamps n.v).
- Tangents: ``tangent.xyz`` is along dP/du (projected onto the shading normal's plane, unit) and
  ``bitangent = cross(normal, tangent.xyz) * tangent.w`` points along -dP/dv in glTF uv, i.e.
  towards the top row of the texture image: +Y of an OpenGL (+Y up) normal map. This is what
  MikkTSpace gives in the OpenGL (v-up) uv convention, which is what glTF's TANGENT holds. A
  plane textured upright has w = +1; mirroring u or v gives w = -1.
- Shadows: a shadow ray starts at the hit point moved along the camera-facing geometric normal
  by ``SHADOW_OFFSET_REL * mesh.scale`` (bounding-box diagonal). A point or spot light is
  occluded by a hit closer than the light; a directional light by any hit. A light on the
  other side of the face from the camera (geometric n.l <= 0) is occluded by the face itself.
- Pixels without a hit hold zeros in every array, ``face == -1`` and ``hit == False``.

Rays are cast by `pbrfit.scene.raycast` (embree when installed, else numpy, refined in float64).
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import os
import threading
import zipfile
from pathlib import Path
from typing import Sequence

import numpy as np
import trimesh
from jaxtyping import Bool, Float, Int

from ..io.atomic import write_cache_file
from .camera import Camera
from ..errors import CaptureError
from .raycast import PARALLEL_EPS, any_perpendicular, cast, has_embree, make_first_hit, normalize, resolved_backend

__all__ = [
    "GBuffer",
    "compute_gbuffer",
    "vertex_tangents",
    "silhouette",
    "has_embree",
    "SHADOW_OFFSET_REL",
    "MEMO_BYTES",
    "UV_CONVENTIONS",
]

# Shadow-ray origin offset, as a fraction of the mesh's bounding-box diagonal. Embree works in
# float32 on a mesh rescaled to ~100 units, where one ulp is ~1e-5 units, so 1e-4 of the scene
# (0.01 units there) clears self-intersection by ~1000 ulps while staying far below any
# geometric detail a material capture resolves.
SHADOW_OFFSET_REL = 1e-4
# A uv triangle with |det| below this fraction of |du1 dv2| + |du2 dv1| has no usable uv
# derivatives (degenerate or collapsed uv); it contributes no tangent.
UV_DEGENERATE_REL = 1e-10
_CACHE_VERSION = "pbrfit-gbuffer/1"
UV_CONVENTIONS = ("gltf", "trimesh")
#: The process keeps the G-buffers it last cast or read, by their cache key, up to this many bytes
#: in all (read-only: callers share them), so a second fit of a capture casts no ray and reads no
#: file (the peer scene's six 128² views: 12 MB, 0.13 s of a 2 s fit).
MEMO_BYTES = 128 << 20
_memo: "collections.OrderedDict[str, GBuffer]" = collections.OrderedDict()
_memo_lock = threading.Lock()  # views are cast in threads (`pbrfit.render.views.capture_gbuffers`)


# ------------------------------------------------------------------------------------ gbuffer


@dataclasses.dataclass
class GBuffer:
    """One view's per-pixel geometry (numpy). See the module docstring for conventions.

    position is float64 (world units); the direction-like arrays and uv are float32.
    """

    hit: Bool[np.ndarray, "H W"]
    position: Float[np.ndarray, "H W 3"]
    normal: Float[np.ndarray, "H W 3"]
    geometric_normal: Float[np.ndarray, "H W 3"]
    tangent: Float[np.ndarray, "H W 4"]
    uv: Float[np.ndarray, "H W 2"]
    view: Float[np.ndarray, "H W 3"]
    visibility: Float[np.ndarray, "H W L"]
    face: Int[np.ndarray, "H W"]

    @property
    def shape(self) -> tuple[int, int]:
        return self.hit.shape

    def _arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


# ---------------------------------------------------------------------------------- tangents


def silhouette(hit: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that hit the mesh while one of their four neighbours misses it, i.e.
    pixels a silhouette edge may cross. Outside the image counts as unknown, not as a miss."""
    hit = np.asarray(hit, bool)
    miss = ~hit
    edge = np.zeros_like(hit)
    edge[1:] |= miss[:-1]
    edge[:-1] |= miss[1:]
    edge[:, 1:] |= miss[:, :-1]
    edge[:, :-1] |= miss[:, 1:]
    return hit & edge


def vertex_tangents(
    vertices: Float[np.ndarray, "V 3"],
    faces: Int[np.ndarray, "F 3"],
    uv: Float[np.ndarray, "V 2"],
    normals: Float[np.ndarray, "V 3"],
) -> tuple[Float[np.ndarray, "2 V 3"], Float[np.ndarray, "F"]]:
    """Per-vertex tangents from uv derivatives, split by handedness, and per-face handedness.

    Per face (Lengyel 2001): with edges e1, e2 and uv deltas (du1, dv1), (du2, dv2),
    det = du1 dv2 - du2 dv1, dP/du = (e1 dv2 - e2 dv1) / det. In glTF uv (v down the image)
    the bitangent -dP/dv equals cross(n, dP/du) * w with w = -sign(det) for n along
    e1 x e2, so w_f = +1 where det < 0. Face tangents (unit) are accumulated at their corners
    weighted by the corner angle (as MikkTSpace does), separately for w = +1 and w = -1 (as
    MikkTSpace splits vertices by handedness), then Gram-Schmidt-orthogonalised against the
    vertex normal. Returns (tangents (2, V, 3): [0] for w = +1, [1] for w = -1; w (F,)).
    Faces with degenerate uv contribute nothing and get w = +1.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    uv = np.asarray(uv, np.float64)
    tri, tuv = vertices[faces], uv[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d1, d2 = tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    good = np.abs(det) > UV_DEGENERATE_REL * (np.abs(d1[:, 0] * d2[:, 1]) + np.abs(d2[:, 0] * d1[:, 1]))
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / np.where(good, det, 1.0)[:, None]
    dpdu = np.where(good[:, None], normalize(dpdu), 0.0)
    w = np.where(good & (det > 0), -1.0, 1.0)
    # corner angles
    angles = np.empty(faces.shape)
    for k in range(3):
        a = normalize(tri[:, (k + 1) % 3] - tri[:, k])
        b = normalize(tri[:, (k + 2) % 3] - tri[:, k])
        angles[:, k] = np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0))
    acc = np.zeros((2, len(vertices), 3))
    group = (w < 0).astype(np.int64)
    for k in range(3):
        np.add.at(acc, (group, faces[:, k]), dpdu * angles[:, k : k + 1])
    n = normalize(np.asarray(normals, np.float64))
    acc = acc - n[None] * np.sum(acc * n[None], -1, keepdims=True)
    return normalize(acc), w


# ------------------------------------------------------------------------------------- cache


def _cache_key(mesh, uv, normals, tangents, camera: Camera, lights) -> str:
    h = hashlib.sha256(_CACHE_VERSION.encode())
    h.update(repr((SHADOW_OFFSET_REL, PARALLEL_EPS, UV_DEGENERATE_REL)).encode())
    for a in (mesh.vertices, mesh.faces, uv, normals, tangents):
        if a is None:
            h.update(b"none")
        else:
            a = np.ascontiguousarray(a, dtype=np.float64)
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())
    h.update(repr(camera._params()).encode())
    for light in lights:
        kind, pos, direction = _light_geometry(light)
        h.update(kind.encode() + pos.tobytes() + direction.tobytes())
    return h.hexdigest()[:32]


def _load_cached(path: Path) -> GBuffer | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            return GBuffer(**{f.name: z[f.name] for f in dataclasses.fields(GBuffer)})
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):  # missing/damaged: recompute
        return None


def _save_cached(path: Path, gbuffer: GBuffer) -> None:
    write_cache_file(path, lambda f: np.savez(f, **gbuffer._arrays()))


def _remembered(key: str, gbuffer: GBuffer) -> GBuffer:
    """``gbuffer``, its arrays made read-only and kept in `_memo` under ``key`` (the oldest
    entries dropped past `MEMO_BYTES`; one larger than that is not kept)."""
    for a in gbuffer._arrays().values():
        a.flags.writeable = False
    size = lambda g: sum(a.nbytes for a in g._arrays().values())  # noqa: E731
    if size(gbuffer) <= MEMO_BYTES:
        with _memo_lock:
            _memo[key] = gbuffer
            total = sum(size(g) for g in _memo.values())
            while total > MEMO_BYTES:
                total -= size(_memo.popitem(last=False)[1])
    return gbuffer


# ----------------------------------------------------------------------------------- compute


def _light_geometry(light) -> tuple[str, np.ndarray, np.ndarray]:
    kind = str(light.kind)
    if kind not in ("point", "spot", "directional"):
        raise ValueError(f"gbuffer: unknown light kind {kind!r}")
    pos = np.asarray(light.position, dtype=np.float64).reshape(3)
    direction = np.asarray(light.direction, dtype=np.float64).reshape(3)
    return kind, pos, direction


def _mesh_uv(mesh, uv_convention: str) -> np.ndarray | None:
    """The mesh's uv in glTF orientation (v = 0 at the top of the image), or None."""
    if uv_convention not in UV_CONVENTIONS:
        raise ValueError(f"gbuffer: uv_convention must be one of {UV_CONVENTIONS}, got {uv_convention!r}")
    uv = getattr(mesh.visual, "uv", None)
    if uv is None:
        return None
    uv = np.array(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[0] != len(mesh.vertices) or uv.shape[1] < 2:
        raise CaptureError(f"mesh: uv has shape {uv.shape}, expected ({len(mesh.vertices)}, 2)")
    uv = uv[:, :2]
    if uv_convention == "trimesh":
        uv[:, 1] = 1.0 - uv[:, 1]
    return uv


def _mesh_tangents(mesh) -> np.ndarray | None:
    t = getattr(mesh, "vertex_attributes", {}).get("tangent")
    if t is None:
        return None
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (len(mesh.vertices), 4):
        raise CaptureError(f"mesh: tangent attribute has shape {t.shape}, expected ({len(mesh.vertices)}, 4)")
    return t


def _visibility(first_hit, tri, start, ng, lights) -> Float[np.ndarray, "P L"]:
    """1 where the shadow ray from `start` (already offset along `ng`) reaches each light."""
    visibility = np.zeros((len(start), len(lights)), dtype=np.float32)
    for k, light in enumerate(lights):
        kind, lpos, ldir = _light_geometry(light)
        if kind == "directional":
            to_light = np.broadcast_to(normalize(-ldir), start.shape)
            dist = np.full(len(start), np.inf)
        else:
            delta = lpos - start
            dist = np.linalg.norm(delta, axis=-1)
            to_light = normalize(delta)
        cand = np.nonzero(np.sum(to_light * ng, -1) > 0)[0]  # else the face itself is in the way
        face, t, _, _ = cast(first_hit, tri, start[cand], np.ascontiguousarray(to_light[cand]))
        blocked = (face >= 0) & (t < dist[cand])
        visibility[cand[~blocked], k] = 1.0
    return visibility


def compute_gbuffer(
    mesh: trimesh.Trimesh,
    camera: Camera,
    lights: Sequence = (),
    cache_dir: str | os.PathLike | None = None,
    *,
    backend: str = "auto",
    uv_convention: str = "gltf",
) -> GBuffer:
    """Ray-cast one view of `mesh` and interpolate its attributes; see the module docstring.

    mesh: triangles with optional ``mesh.visual.uv`` (without uv, uv is 0 and the tangent an
    arbitrary unit vector perpendicular to the normal) and optional
    ``mesh.vertex_attributes["tangent"]`` (V, 4) in glTF TANGENT convention, used instead of
    computed tangents when present (trimesh's loaders do not read TANGENT; a loader that does
    can put it there). Shading normals are ``mesh.vertex_normals``.
    lights: objects with ``kind`` ("point" | "spot" | "directional"), ``position`` and
    ``direction`` (where the light travels), e.g. `pbrfit.physics.lights.Light`.
    cache_dir: when given, the result is read from / written to
    ``cache_dir/gbuffer-<hash>.npz``, the hash covering the mesh (vertices, faces, uv,
    normals, tangents), the camera and the lights' kinds, positions and directions. With or
    without it, the process keeps the latest G-buffers under that hash and the backend
    (`MEMO_BYTES`): the arrays of a result are read-only.
    backend: "embree" (embreex via trimesh, float32 traversal), "numpy" (box-culled exact
    tests, float64, slower) or "auto" (embree when installed). Either way the hit on the reported face is recomputed in
    float64, so positions lie on the mesh to float64 rounding.
    uv_convention: how ``mesh.visual.uv`` is oriented. "gltf": v = 0 at the top row of the
    image, used as is. "trimesh": v = 0 at the bottom (what trimesh's glTF and OBJ loaders
    produce: its glTF loader stores 1 - v), turned into glTF's (u, 1 - v). The G-buffer's uv is
    always glTF-oriented.
    """
    lights = tuple(lights)
    uv_v = _mesh_uv(mesh, uv_convention)
    tan_v = _mesh_tangents(mesh)
    normals_v = np.asarray(mesh.vertex_normals, dtype=np.float64)
    key = _cache_key(mesh, uv_v, normals_v, tan_v, camera, lights)
    path = None if cache_dir is None else Path(cache_dir) / f"gbuffer-{key}.npz"
    # the memo keeps each intersector's own (the files, either: they agree to float64 refinement)
    remembered = f"{key}-{resolved_backend(backend)}"
    with _memo_lock:
        known = _memo.get(remembered)
        if known is not None:
            _memo.move_to_end(remembered)
    if known is not None:
        if path is not None and not path.exists():
            _save_cached(path, known)
        return known
    if path is not None:
        cached = _load_cached(path)
        if cached is not None:
            return _remembered(remembered, cached)

    H, W = camera.height, camera.width
    faces_v = np.asarray(mesh.faces, dtype=np.int64)
    tri = np.asarray(mesh.vertices, dtype=np.float64)[faces_v]
    first_hit = make_first_hit(mesh, backend)

    origins, directions = camera.rays()
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    face, t, b1, b2 = cast(first_hit, tri, origins, directions)
    idx = np.nonzero(face >= 0)[0]
    f = face[idx]
    bary = np.stack([1.0 - b1[idx] - b2[idx], b1[idx], b2[idx]], -1)[..., None]  # (P, 3, 1)
    fv = faces_v[f]

    def interp(attr):
        return np.sum(attr[fv] * bary, axis=1)

    position = origins[idx] + t[idx, None] * directions[idx]
    view = normalize(camera.center - position)
    ng = normalize(np.cross(tri[f, 1] - tri[f, 0], tri[f, 2] - tri[f, 0]))
    flip = np.where(np.sum(ng * view, -1) < 0, -1.0, 1.0)[:, None]
    n = normalize(interp(normals_v))
    n = np.where(np.linalg.norm(n, axis=-1, keepdims=True) > 0.5, n, ng)  # opposite normals cancel

    if uv_v is None:
        uv = np.zeros((len(idx), 2))
        tan, w = any_perpendicular(n), np.ones(len(idx))
    else:
        uv = interp(uv_v)
        if tan_v is not None:
            tan = interp(tan_v[:, :3])
            w = np.where(interp(tan_v[:, 3:])[:, 0] < 0, -1.0, 1.0)
        else:
            vt, wf = vertex_tangents(mesh.vertices, faces_v, uv_v, normals_v)
            w = wf[f]
            tan = np.sum(vt[(w < 0).astype(np.int64)[:, None], fv] * bary, axis=1)
        tan = normalize(tan - n * np.sum(tan * n, -1, keepdims=True))
        missing = np.linalg.norm(tan, axis=-1) < 0.5
        tan[missing] = any_perpendicular(n[missing])

    # two-sided: mirror the whole frame where the camera sees the back of the face
    ng, n, tan, w = ng * flip, n * flip, tan * flip, w * flip[:, 0]

    start = position + ng * (SHADOW_OFFSET_REL * float(mesh.scale))
    visibility = _visibility(first_hit, tri, start, ng, lights)

    def full(values, channels, dtype):
        tail = () if channels is None else (channels,)
        out = np.zeros((H * W, *tail), dtype=dtype)
        out[idx] = values
        return out.reshape((H, W, *tail))

    face_img = np.full(H * W, -1, dtype=np.int64)
    face_img[idx] = f
    gbuffer = GBuffer(
        hit=full(True, None, bool),
        position=full(position, 3, np.float64),
        normal=full(n, 3, np.float32),
        geometric_normal=full(ng, 3, np.float32),
        tangent=full(np.concatenate([tan, w[:, None]], -1), 4, np.float32),
        uv=full(uv, 2, np.float32),
        view=full(view, 3, np.float32),
        visibility=full(visibility, len(lights), np.float32),
        face=face_img.reshape(H, W),
    )
    if path is not None:
        _save_cached(path, gbuffer)
    return _remembered(remembered, gbuffer)
