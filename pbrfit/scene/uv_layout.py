"""A mesh's uv layout as the fit reads it: one set of maps over the whole mesh.

`check_uv_layout` refuses texture coordinates that span no area. `shared_uv_space` finds
materials whose texture coordinates cover the same part of the uv square: a file with several
materials usually gives each its own textures, each over the whole square, while pbrfit fits
one set of maps for the whole mesh, so each shared texel would be fitted to the pixels of both
materials at once. `pbrfit.scene.mesh.load_mesh` warns of it.
"""

from __future__ import annotations

import itertools
from typing import Optional, Sequence

import numpy as np
from PIL import Image, ImageDraw
from scipy import ndimage

from ..errors import CaptureError

__all__ = ["check_uv_layout", "uv_area", "material_coverage", "shared_uv_space", "UV_AREA_MIN", "OVERLAP_GRID",
           "OVERLAP_SHARE", "OVERLAP_TRIANGLES"]

#: Below this total uv area (in units of the texture square) a mesh's texture coordinates lay out
#: nothing: every texel would be seen through no triangle or through all of them.
UV_AREA_MIN = 1e-10
#: Materials' texture space is compared on a grid of this many cells a side over the uv square
#: (coordinates taken modulo 1, as the maps repeat) ...
OVERLAP_GRID = 256
#: ... a material shares it where more than this fraction of the cells it covers lie inside a
#: region other materials cover too ...
OVERLAP_SHARE = 0.05
#: ... and at most this many triangles are drawn in all (every k-th of each material; one polygon
#: fill each, some 3 µs).
OVERLAP_TRIANGLES = 200_000


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


def material_coverage(uv: np.ndarray, faces: np.ndarray, grid: int = OVERLAP_GRID, step: int = 1) -> np.ndarray:
    """(grid, grid) bool: the cells of the uv square the triangles cover (every ``step``-th),
    the uv square repeated as the maps repeat: each triangle is moved by a whole number of
    squares to put its centroid in [0, 1)², and drawn again a square over in each direction
    where it crosses the square's border."""
    image = Image.new("1", (grid, grid))
    draw = ImageDraw.Draw(image)
    triangles = np.asarray(uv, np.float64)[np.asarray(faces)[::step]]  # (F, 3, 2)
    triangles = triangles - np.floor(triangles.mean(axis=1, keepdims=True))
    lo, hi = triangles.min(axis=1), triangles.max(axis=1)  # (F, 2)
    for shift in itertools.product((-1, 0, 1), repeat=2):
        # the copies a square over: only the triangles that reach into the square from there
        near = np.all((lo + shift < 1.0) & (hi + shift > 0.0), axis=1) if shift != (0, 0) else slice(None)
        for triangle in (triangles[near] + shift) * grid:
            draw.polygon([tuple(point) for point in triangle], fill=1, outline=1)
    return np.asarray(image, bool)


def _interior(cells: np.ndarray) -> np.ndarray:
    """``cells`` less their rim: cells whose eight neighbours (the grid wraps) are in it too."""
    padded = np.pad(cells, 1, mode="wrap")
    return ndimage.binary_erosion(padded, np.ones((3, 3), bool))[1:-1, 1:-1]


def shared_uv_space(materials: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> Optional[tuple[str, str, float]]:
    """Of ``(material, uv (V, 2), faces (F, 3))`` parts of a mesh: the material the others
    overlap most in the uv square, with the one that overlaps it most and the share of its
    texture space they cover, where that share is above `OVERLAP_SHARE`; None otherwise.

    Parts of the same material (instances of one mesh) may share theirs. A shared cell counts
    only inside a shared region (`_interior`): materials that meet along a seam both cover the
    cells it crosses, and share nothing. At most `OVERLAP_TRIANGLES` triangles are drawn in all
    (every k-th of each part), and the coverages are compared by the count of materials over
    each cell, so the check grows with the triangles and materials, not with their pairs."""
    step = max(1, -(-sum(len(faces) for _, _, faces in materials) // OVERLAP_TRIANGLES))
    covered = {}
    for name, uv, faces in materials:
        cells = material_coverage(uv, faces, step=step)
        covered[name] = cells | covered[name] if name in covered else cells
    if len(covered) < 2:
        return None
    count = sum(cells.astype(np.int32) for cells in covered.values())
    worst = None
    for name, cells in covered.items():
        own = int(cells.sum())
        share = int(np.sum(_interior(cells & (count - cells > 0)))) / own if own else 0.0
        if share > OVERLAP_SHARE and (worst is None or share > worst[2]):
            worst = (name, None, share)
    if worst is None:
        return None
    name = worst[0]
    partner = max((other for other in covered if other != name),
                  key=lambda other: int(np.sum(covered[name] & covered[other])))
    return name, partner, worst[2]
