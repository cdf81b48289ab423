"""A mesh's uv layout as the fit reads it: one set of maps over the whole mesh.

`check_uv_layout` refuses texture coordinates that span no area. `shared_uv_space` finds
materials whose texture coordinates cover the same part of the uv square: a file with several
materials usually gives each its own textures, each over the whole square, while pbrfit fits
one set of maps for the whole mesh, so each shared texel would be fitted to the pixels of both
materials at once. `pbrfit.mesh.load_mesh` warns of it.
"""

from __future__ import annotations

import itertools
from typing import Optional, Sequence

import numpy as np

from .errors import CaptureError

__all__ = ["check_uv_layout", "uv_area", "material_coverage", "shared_uv_space", "UV_AREA_MIN", "OVERLAP_GRID",
           "OVERLAP_SHARE", "OVERLAP_TRIANGLES"]

#: Below this total uv area (in units of the texture square) a mesh's texture coordinates lay out
#: nothing: every texel would be seen through no triangle or through all of them.
UV_AREA_MIN = 1e-10
#: Materials' texture space is compared on a grid of this many cells a side over the uv square
#: (coordinates taken modulo 1, as the maps repeat) ...
OVERLAP_GRID = 256
#: ... two materials share it where more than this fraction of the cells the smaller of them
#: covers are covered by both (drawn triangles cover the cells their edges touch, so two
#: materials that only meet along a seam share a thin line of cells) ...
OVERLAP_SHARE = 0.05
#: ... and at most this many triangles of each material are drawn (evenly strided; one polygon
#: fill each).
OVERLAP_TRIANGLES = 100_000


def uv_area(uv: np.ndarray, faces: np.ndarray) -> float:
    """Σ over triangles of the uv triangle's area, ½ |(uv1 - uv0) × (uv2 - uv0)|."""
    a, b, c = (uv[faces[:, k]] for k in range(3))
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    return float(0.5 * np.sum(np.abs(cross)))


def check_uv_layout(mesh, where: str = "mesh") -> None:
    """Raise `CaptureError` unless a loaded mesh's texture coordinates lay out an area texture
    maps can be read through (total uv area above `UV_AREA_MIN`)."""
    path = mesh.metadata.get("file", "")
    uv = getattr(mesh.visual, "uv", None)
    if uv is None:
        raise CaptureError(f"{where}: mesh {path} has no texture coordinates (glTF TEXCOORD_0 / OBJ vt); "
                           "texture maps need them")
    if uv_area(np.asarray(uv, np.float64), np.asarray(mesh.faces)) <= UV_AREA_MIN:
        raise CaptureError(f"{where}: mesh {path}: texture coordinates span no area (every triangle's uv area "
                           "is 0, e.g. all equal); texture maps need a uv layout")


def material_coverage(uv: np.ndarray, faces: np.ndarray, grid: int = OVERLAP_GRID) -> np.ndarray:
    """(grid, grid) bool: the cells of the uv square the triangles cover, each triangle moved by
    a whole number of squares to put its centroid in [0, 1)² (the maps repeat); at most
    `OVERLAP_TRIANGLES` triangles, evenly strided."""
    from PIL import Image, ImageDraw

    image = Image.new("1", (grid, grid))
    draw = ImageDraw.Draw(image)
    step = max(1, -(-len(faces) // OVERLAP_TRIANGLES))
    triangles = np.asarray(uv, np.float64)[np.asarray(faces)[::step]]  # (F, 3, 2)
    triangles = (triangles - np.floor(triangles.mean(axis=1, keepdims=True))) * grid
    for triangle in triangles:
        draw.polygon([tuple(point) for point in triangle], fill=1, outline=1)
    return np.asarray(image, bool)


def shared_uv_space(materials: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> Optional[tuple[str, str, float]]:
    """Of ``(material name, uv (V, 2), faces (F, 3))`` parts of a mesh: the two differently named
    materials that share the largest fraction of the texture space the smaller of them covers,
    with that fraction, where it is above `OVERLAP_SHARE`; None otherwise (parts of the same
    name, as instances of one mesh, may share theirs)."""
    covered = {}
    for name, uv, faces in materials:
        cells = material_coverage(uv, faces)
        covered[name] = cells | covered[name] if name in covered else cells
    worst = None
    for a, b in itertools.combinations(sorted(covered), 2):
        least = min(int(covered[a].sum()), int(covered[b].sum()))
        share = int(np.sum(covered[a] & covered[b])) / least if least else 0.0
        if share > OVERLAP_SHARE and (worst is None or share > worst[2]):
            worst = (a, b, share)
    return worst
