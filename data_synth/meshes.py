"""Meshes with texture coordinates: plane, UV sphere, rounded box, torus, a user's mesh.

A `MeshData` holds float32 vertices, int32 triangles (counter-clockwise seen from outside),
analytic unit vertex normals, and uv in **glTF orientation** (v = 0 at the top row of the
texture image). trimesh keeps uv the OpenGL way (v = 0 at the bottom) and flips v when it
reads or writes glTF; `MeshData.to_trimesh` does that flip, so a GLB written from a `MeshData`
carries exactly its uv as ``TEXCOORD_0``. `load_mesh` reads through `pbrfit.scene.mesh.load_mesh`,
which hands back glTF-oriented uv.

Every generator builds in the y-up frame and takes `world_up`: for ``"+z"`` the mesh is
turned by the Blender <-> glTF axis change (x, y, z)_y-up -> (x, -z, y)_z-up, so "up" in the
generator is +Z in the world and a texture seen from above keeps its orientation.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = [
    "MeshData",
    "plane",
    "uv_sphere",
    "rounded_box",
    "torus",
    "load_mesh",
    "combine",
    "write_glb",
    "to_world_up",
]

#: Texels of padding between atlas tiles (as a fraction of a tile): keeps bilinear lookups at
#: a tile's border from reading the neighbour tile.
ATLAS_PADDING = 0.02


@dataclasses.dataclass(frozen=True)
class MeshData:
    """A triangle mesh with per-vertex normals and glTF-oriented uv (all float32 / int32)."""

    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    normals: np.ndarray  # (V, 3) unit
    uv: np.ndarray  # (V, 2) glTF orientation: v = 0 at the top row of the texture

    def __post_init__(self):
        object.__setattr__(self, "vertices", np.ascontiguousarray(self.vertices, np.float32))
        object.__setattr__(self, "faces", np.ascontiguousarray(self.faces, np.int32))
        n = np.asarray(self.normals, np.float64)
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        object.__setattr__(self, "normals", np.ascontiguousarray(n, np.float32))
        object.__setattr__(self, "uv", np.ascontiguousarray(self.uv, np.float32))

    def transformed(self, matrix: np.ndarray) -> "MeshData":
        """The mesh under a 4x4 affine transform (normals by the inverse transpose)."""
        m = np.asarray(matrix, np.float64)
        v = self.vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        n = self.normals.astype(np.float64) @ np.linalg.inv(m[:3, :3])
        faces = self.faces if np.linalg.det(m[:3, :3]) > 0 else self.faces[:, ::-1]
        return MeshData(v, faces, n, self.uv)

    def translated(self, offset: Sequence[float]) -> "MeshData":
        m = np.eye(4)
        m[:3, 3] = offset
        return self.transformed(m)

    def with_uv(self, uv: np.ndarray) -> "MeshData":
        return dataclasses.replace(self, uv=uv)

    def to_trimesh(self):
        """A `trimesh.Trimesh` (uv flipped to trimesh's v-up convention, normals kept)."""
        import trimesh

        uv_gl = self.uv.astype(np.float64).copy()
        uv_gl[:, 1] = 1.0 - uv_gl[:, 1]
        mesh = trimesh.Trimesh(
            vertices=self.vertices.astype(np.float64),
            faces=self.faces,
            vertex_normals=self.normals.astype(np.float64),
            visual=trimesh.visual.TextureVisuals(uv=uv_gl),
            process=False,
        )
        return mesh


def to_world_up(mesh: MeshData, world_up: str) -> MeshData:
    """Turn a y-up mesh to the world: identity for +y, (x, y, z) -> (x, -z, y) for +z."""
    if world_up == "+y":
        return mesh
    if world_up == "+z":
        m = np.eye(4)
        m[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
        return mesh.transformed(m)
    raise ValueError(f"world_up must be '+y' or '+z', got {world_up!r}")


def _grid_faces(rows: int, cols: int, offset: int = 0) -> np.ndarray:
    """Two triangles per cell of a (rows+1) x (cols+1) vertex grid (row-major).

    With "down" the direction of growing row index and "right" that of growing column index,
    each triangle's normal (counter-clockwise winding) is down x right."""
    i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    a = i * (cols + 1) + j
    b = a + 1
    c = a + (cols + 1)
    d = c + 1
    # a--b   (row i)      (a, c, b) and (b, c, d): (c - a) x (b - a) = down x right
    # |  |
    # c--d   (row i+1)
    tri = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)], axis=0)
    return tri.reshape(-1, 3) + offset


def plane(size: float = 2.0, segments: int = 1, world_up: str = "+y", uv_repeat: float = 1.0) -> MeshData:
    """A square of side `size` centred at the origin, facing up.

    uv as Blender's default plane exported to glTF: u runs along +X, v runs along +Z in the
    y-up frame (v = 0 at the far edge z = -size/2, the top of the image seen from above with
    -Z forward); under ``world_up="+z"``, v = 0 at y = +size/2.
    """
    n = int(segments)
    t = np.linspace(0.0, 1.0, n + 1)
    vv, uu = np.meshgrid(t, t, indexing="ij")  # rows along v, columns along u
    x = (uu - 0.5) * size
    z = (vv - 0.5) * size
    verts = np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3)
    uv = np.stack([uu, vv], -1).reshape(-1, 2) * uv_repeat
    normals = np.tile([0.0, 1.0, 0.0], (len(verts), 1))
    # rows run towards +z (down the image seen from above), columns towards +x: z x x = +y
    faces = _grid_faces(n, n)
    return to_world_up(MeshData(verts, faces, normals, uv), world_up)


def uv_sphere(
    radius: float = 1.0,
    segments: int = 64,
    rings: int = 32,
    center: Sequence[float] = (0.0, 0.0, 0.0),
    world_up: str = "+y",
) -> MeshData:
    """A UV sphere: u = 0.5 + phi / (2 pi) with phi the azimuth about +Y, zero towards +Z
    (the front, u = 0.5; the seam is at the back, -Z), v = theta / pi from the north pole
    (the top row of the texture). Seen from outside the texture is not mirrored."""
    theta = np.linspace(0.0, np.pi, rings + 1)
    u = np.linspace(0.0, 1.0, segments + 1)
    phi = (u - 0.5) * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    n = np.stack([np.sin(th) * np.sin(ph), np.cos(th), np.sin(th) * np.cos(ph)], -1).reshape(-1, 3)
    uu, vv = np.meshgrid(u, theta / np.pi, indexing="xy")
    uv = np.stack([uu, vv], -1).reshape(-1, 2)
    faces = _grid_faces(rings, segments)
    # drop the degenerate triangles at the poles (two vertices at the same pole)
    verts = n * radius
    tri = verts[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    faces = faces[area > 1e-12 * radius * radius]
    mesh = _drop_unreferenced(MeshData(verts, faces, n, uv))
    return to_world_up(mesh, world_up).translated(center)


def torus(
    major_radius: float = 1.0,
    minor_radius: float = 0.35,
    segments: int = 64,
    rings: int = 24,
    world_up: str = "+y",
) -> MeshData:
    """A torus about the up axis: u runs around the ring (as the sphere's azimuth), v around
    the tube starting at its top, over the outside, to the bottom and back inside."""
    u = np.linspace(0.0, 1.0, segments + 1)
    v = np.linspace(0.0, 1.0, rings + 1)
    phi = (u - 0.5) * 2 * np.pi
    psi = v * 2 * np.pi  # 0 at the top of the tube, pi/2 outside
    ps, ph = np.meshgrid(psi, phi, indexing="ij")
    radial = np.stack([np.sin(ph), np.zeros_like(ph), np.cos(ph)], -1)
    up = np.array([0.0, 1.0, 0.0])
    n = np.cos(ps)[..., None] * up + np.sin(ps)[..., None] * radial
    verts = major_radius * radial + minor_radius * n
    uu, vv = np.meshgrid(u, v, indexing="xy")
    uv = np.stack([uu, vv], -1).reshape(-1, 2)
    return to_world_up(MeshData(verts.reshape(-1, 3), _grid_faces(rings, segments), n.reshape(-1, 3), uv), world_up)


# Cube faces for the rounded box: (normal axis, sign), (right axis, sign), (down axis, sign) with
# down x right = the outward normal, and the atlas tile (column, row) of each face.
_BOX_FACES = (
    ((0, +1), (2, -1), (1, -1), (0, 0)),  # +X: right -Z, down -Y
    ((0, -1), (2, +1), (1, -1), (1, 0)),  # -X: right +Z, down -Y
    ((1, +1), (0, +1), (2, +1), (2, 0)),  # +Y: right +X, down +Z (seen from above, -Z forward)
    ((1, -1), (0, +1), (2, -1), (0, 1)),  # -Y: right +X, down -Z
    ((2, +1), (0, +1), (1, -1), (1, 1)),  # +Z: right +X, down -Y (the front)
    ((2, -1), (0, -1), (1, -1), (2, 1)),  # -Z: right -X, down -Y
)


def rounded_box(
    size: Sequence[float] = (1.4, 1.0, 1.0),
    radius: float = 0.2,
    segments: int = 6,
    flat_segments: int = 4,
    world_up: str = "+y",
) -> MeshData:
    """A box with rounded edges and corners (radius `radius`), one atlas tile per face.

    Built from a subdivided cube: a point p on the cube of half extents h moves to
    ``q + radius * normalize(p - q)`` with q = clamp(p, -(h - radius), h - radius), and its
    normal is ``normalize(p - q)``. Faces share positions along cube edges but not uv. The
    atlas is 3 x 2 tiles (+X, -X, +Y / -Y, +Z, -Z), each with `ATLAS_PADDING`.
    """
    h = np.asarray(size, np.float64) / 2
    r = float(min(radius, h.min() * 0.999))
    verts, normals, uvs, faces = [], [], [], []
    offset = 0
    for (ax, sign), (rax, rsign), (dax, dsign), (tc, tr) in _BOX_FACES:
        def coords(axis, k_sign):
            # parameter from -h to h: `segments` steps in each rounded band, `flat_segments` between
            inner = h[axis] - r
            t = np.concatenate([
                np.linspace(-h[axis], -inner, segments + 1)[:-1],
                np.linspace(-inner, inner, flat_segments + 1),
                np.linspace(inner, h[axis], segments + 1)[1:],
            ])
            return t * k_sign
        a = coords(rax, rsign)  # grows to the right
        b = coords(dax, dsign)  # grows downwards
        bb, aa = np.meshgrid(b, a, indexing="ij")
        p = np.zeros(bb.shape + (3,))
        p[..., ax] = sign * h[ax]
        p[..., rax] = aa
        p[..., dax] = bb
        q = np.clip(p, -(h - r), h - r)
        d = p - q
        nrm = d / np.linalg.norm(d, axis=-1, keepdims=True)
        pos = q + r * nrm
        # uv in the face's tile: fraction along the face's surface (arc length would be nicer;
        # the cube parameter is monotone and good enough for a texture)
        fu = (aa * rsign + h[rax]) / (2 * h[rax])
        fv = (bb * dsign + h[dax]) / (2 * h[dax])
        pad = ATLAS_PADDING
        uv = np.stack([(tc + pad + (1 - 2 * pad) * fu) / 3, (tr + pad + (1 - 2 * pad) * fv) / 2], -1)
        rows, cols = bb.shape[0] - 1, bb.shape[1] - 1
        verts.append(pos.reshape(-1, 3))
        normals.append(nrm.reshape(-1, 3))
        uvs.append(uv.reshape(-1, 2))
        faces.append(_grid_faces(rows, cols, offset))
        offset += (rows + 1) * (cols + 1)
    mesh = MeshData(np.concatenate(verts), np.concatenate(faces), np.concatenate(normals), np.concatenate(uvs))
    return to_world_up(mesh, world_up)


def _drop_unreferenced(mesh: MeshData) -> MeshData:
    used = np.zeros(len(mesh.vertices), bool)
    used[mesh.faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return MeshData(mesh.vertices[used], remap[mesh.faces], mesh.normals[used], mesh.uv[used])


def combine(meshes: Sequence[MeshData], tiles: Sequence[tuple[float, float, float, float]]) -> MeshData:
    """One mesh from several, each mesh's uv squeezed into its tile (u0, v0, u1, v1) of the
    shared texture (glTF orientation), so one set of maps textures them all (an atlas)."""
    verts, normals, uvs, faces = [], [], [], []
    offset = 0
    for mesh, (u0, v0, u1, v1) in zip(meshes, tiles, strict=True):
        uv = mesh.uv.astype(np.float64)
        uvs.append(np.stack([u0 + (u1 - u0) * uv[:, 0], v0 + (v1 - v0) * uv[:, 1]], -1))
        verts.append(mesh.vertices)
        normals.append(mesh.normals)
        faces.append(mesh.faces + offset)
        offset += len(mesh.vertices)
    return MeshData(np.concatenate(verts), np.concatenate(faces), np.concatenate(normals), np.concatenate(uvs))


def load_mesh(path, normalize: bool = False) -> MeshData:
    """A user's mesh (anything `pbrfit.scene.mesh.load_mesh` reads: glTF/GLB, OBJ, PLY) with its uv.

    Read exactly as a capture's mesh is read (scenes flattened, uv turned to glTF orientation,
    the file's normals kept), so a synthetic capture of it shows what a fit will see. With
    `normalize`, it is centred on its bounding box and scaled to fit a unit-radius sphere.
    Raises `CaptureError` when the file cannot be read, has no texture coordinates or has no
    area (every triangle degenerate: nothing would show in the images).
    """
    from pbrfit.errors import CaptureError
    from pbrfit.scene.mesh import load_mesh as load_capture_mesh

    mesh = load_capture_mesh(Path(path), where="--mesh")
    if not float(np.sum(mesh.area_faces)) > 0.0:
        raise CaptureError(f"--mesh: {path}: every triangle has zero area, so nothing would show in the images")
    data = MeshData(mesh.vertices, mesh.faces, mesh.vertex_normals, np.asarray(mesh.visual.uv)[:, :2])
    if normalize:
        lo, hi = data.vertices.min(0), data.vertices.max(0)
        c = (lo + hi) / 2
        s = 1.0 / max(np.linalg.norm(data.vertices - c, axis=-1).max(), 1e-12)
        m = np.eye(4) * s
        m[3, 3] = 1
        m[:3, 3] = -c * s
        data = data.transformed(m)
    return data


def write_glb(path, mesh: MeshData) -> None:
    """Write the mesh as a binary glTF (positions, normals, TEXCOORD_0), atomically."""
    from pbrfit.io.atomic import atomic_open

    tm = mesh.to_trimesh()
    data = tm.export(file_type="glb", include_normals=True)
    with atomic_open(Path(path)) as f:
        f.write(data)
