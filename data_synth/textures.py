"""Procedural ground-truth material maps.

Every map is a numpy float32 array in glTF texture orientation: row 0 is v = 0 and texel
(i, j) has its centre at uv = ((j + 0.5)/W, (i + 0.5)/H). Scalar maps are (H, W); `TruthMaps`
holds them as (H, W, 1) like `pbrfit.physics.material.Material`. Every generator takes a
`numpy.random.Generator`, so a scene is reproducible from its seed. Noise is periodic (it tiles
under ``wrap="repeat"``).

Sources: value noise and fractal Brownian motion as in K. Perlin, "An Image Synthesizer",
SIGGRAPH 1985, and F. K. Musgrave's fBm (Ebert et al., "Texturing and Modeling", ch. 16);
Voronoi (cellular) patches as in S. Worley, "A Cellular Texture Basis Function", SIGGRAPH 1996.
Gold's base colour is the glTF 2.0 specification's (Appendix B, "metals" table).
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

__all__ = [
    "GOLD",
    "SILVER",
    "COPPER",
    "ALUMINIUM",
    "MIN_TRUTH_ROUGHNESS",
    "TruthMaps",
    "texel_uv",
    "value_noise",
    "fbm",
    "voronoi_labels",
    "gradient",
    "binary_mask",
    "scratches",
    "palette",
    "uniform_maps",
    "textured_maps",
    "chart_maps",
    "paste_tile",
]

#: Linear base colours (= F0) of common metals, glTF 2.0 specification Appendix B.
GOLD = (1.000, 0.766, 0.336)
SILVER = (0.972, 0.960, 0.915)
COPPER = (0.955, 0.638, 0.538)
ALUMINIUM = (0.913, 0.922, 0.924)

#: Lowest roughness the procedural maps produce. Below ~0.1 a GGX highlight is narrower than a
#: pixel at the preset resolutions, so no capture constrains it; the truth stays where the
#: images can say something.
MIN_TRUTH_ROUGHNESS = 0.1

#: Darkest dielectric base colour the palettes produce: a black texel hides its roughness
#: only in its diffuse part, but a near-zero albedo makes relative errors meaningless.
MIN_ALBEDO = 0.03


@dataclasses.dataclass(frozen=True)
class TruthMaps:
    """The maps that render a synthetic capture (glTF metallic-roughness, linear values).

    Attributes:
        base_color: (H, W, 3) linear RGB in [0, 1].
        metallic: (H, W, 1) in [0, 1].
        roughness: (H, W, 1) perceptual roughness in [0, 1] (alpha = roughness^2).
    """

    base_color: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray

    def __post_init__(self):
        h, w = self.base_color.shape[:2]
        for name, c in (("base_color", 3), ("metallic", 1), ("roughness", 1)):
            a = getattr(self, name)
            if a.shape != (h, w, c):
                raise ValueError(f"TruthMaps.{name} has shape {a.shape}, expected {(h, w, c)}")

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.base_color.shape[:2])

    def to_material(self):
        """The same maps as a `pbrfit.physics.material.Material` (jax arrays)."""
        import jax.numpy as jnp

        from pbrfit.physics.material import Material

        return Material(
            base_color=jnp.asarray(self.base_color),
            metallic=jnp.asarray(self.metallic),
            roughness=jnp.asarray(self.roughness),
            normal=None,
            occlusion=None,
            emissive=None,
        )


def _shape(size) -> tuple[int, int]:
    if isinstance(size, (int, np.integer)):
        return int(size), int(size)
    h, w = size
    return int(h), int(w)


def texel_uv(size) -> np.ndarray:
    """(H, W, 2) uv of texel centres, glTF orientation: uv[i, j] = ((j + .5)/W, (i + .5)/H)."""
    h, w = _shape(size)
    u = (np.arange(w, dtype=np.float64) + 0.5) / w
    v = (np.arange(h, dtype=np.float64) + 0.5) / h
    return np.stack(np.meshgrid(u, v, indexing="xy"), axis=-1).astype(np.float32)


def _smoothstep5(t):
    """Quintic fade 6t^5 - 15t^4 + 10t^3 (Perlin 2002): C2 continuous lattice interpolation."""
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def value_noise(size, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Periodic value noise in [0, 1]: a random `cells` x `cells` lattice, quintic interpolation.

    Periodic in both u and v (the lattice wraps), so the map tiles.
    """
    h, w = _shape(size)
    cells = max(int(cells), 1)
    lattice = rng.random((cells, cells))
    uv = texel_uv((h, w)).astype(np.float64) * cells
    x, y = uv[..., 0], uv[..., 1]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = _smoothstep5(x - x0), _smoothstep5(y - y0)
    x0, y0 = x0 % cells, y0 % cells
    x1, y1 = (x0 + 1) % cells, (y0 + 1) % cells
    top = lattice[y0, x0] * (1 - fx) + lattice[y0, x1] * fx
    bottom = lattice[y1, x0] * (1 - fx) + lattice[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def fbm(
    size,
    rng: np.random.Generator,
    octaves: int = 4,
    base_cells: int = 4,
    lacunarity: int = 2,
    gain: float = 0.5,
) -> np.ndarray:
    """Fractal Brownian motion: sum of value-noise octaves, rescaled to span [0, 1] exactly."""
    total = np.zeros(_shape(size), np.float64)
    amplitude, cells = 1.0, base_cells
    for _ in range(octaves):
        total += amplitude * value_noise(size, cells, rng)
        amplitude *= gain
        cells *= lacunarity
    lo, hi = total.min(), total.max()
    return ((total - lo) / max(hi - lo, 1e-12)).astype(np.float32)


def voronoi_labels(size, sites: int, rng: np.random.Generator) -> np.ndarray:
    """(H, W) int labels of the nearest of `sites` random sites (periodic distance): patches."""
    uv = texel_uv(size).astype(np.float64)
    pts = rng.random((int(sites), 2))
    d = np.abs(uv[:, :, None, :] - pts[None, None])
    d = np.minimum(d, 1.0 - d)  # wrap around: the patches tile
    return np.argmin((d * d).sum(-1), axis=-1)


def gradient(size, start: float = 0.0, end: float = 1.0, angle_deg: float = 0.0) -> np.ndarray:
    """Linear ramp from `start` to `end` across the map; angle 0 runs along +u, 90 along +v."""
    uv = texel_uv(size).astype(np.float64)
    a = np.deg2rad(angle_deg)
    d = np.array([np.cos(a), np.sin(a)])
    t = (uv - 0.5) @ d
    span = 0.5 * (abs(d[0]) + abs(d[1]))  # the projection of the unit square's corners
    t = np.clip(t / (2 * span) + 0.5, 0.0, 1.0)
    return (start + (end - start) * t).astype(np.float32)


def binary_mask(
    size, rng: np.random.Generator, coverage: float = 0.35, cells: int = 4, octaves: int = 2
) -> np.ndarray:
    """(H, W) bool: blobs covering a `coverage` fraction of texels (thresholded fBm)."""
    n = fbm(size, rng, octaves=octaves, base_cells=cells)
    threshold = np.quantile(n, 1.0 - float(coverage))
    return n > threshold


def scratches(
    size,
    rng: np.random.Generator,
    count: int = 12,
    width: float = 0.006,
    length: tuple[float, float] = (0.15, 0.5),
) -> np.ndarray:
    """(H, W) in [0, 1]: `count` straight scratches (antialiased line segments, width in uv)."""
    uv = texel_uv(size).astype(np.float64)
    h, w = uv.shape[:2]
    texel = 1.0 / max(h, w)
    out = np.zeros((h, w))
    for _ in range(int(count)):
        a = rng.random(2)
        ang = rng.uniform(0, np.pi)
        ln = rng.uniform(*length)
        b = a + ln * np.array([np.cos(ang), np.sin(ang)])
        ab = b - a
        # periodic: measure from the segment's nearest image
        p = uv - a
        p = p - np.round(p - 0.5 * ab)
        t = np.clip((p @ ab) / (ab @ ab), 0.0, 1.0)
        dist = np.linalg.norm(p - t[..., None] * ab, axis=-1)
        out = np.maximum(out, np.clip(0.5 + (0.5 * width - dist) / texel, 0.0, 1.0))
    return out.astype(np.float32)


def palette(n: int, rng: np.random.Generator, saturation=(0.25, 0.75), value=(0.35, 0.9)) -> np.ndarray:
    """(n, 3) linear RGB colours: random hues, sRGB-space saturation/value ranges, in [MIN_ALBEDO, 1]."""
    hue = rng.random(n)
    sat = rng.uniform(*saturation, n)
    val = rng.uniform(*value, n)
    # HSV -> RGB (f(n) = v - v s max(0, min(k, 4 - k, 1)), k = (n + 6h) mod 6, n = 5, 3, 1)
    k = (np.array([5.0, 3.0, 1.0])[None, :] + 6.0 * hue[:, None]) % 6.0
    rgb = val[:, None] * (1 - sat[:, None] * np.clip(np.minimum(k, 4 - k), 0, 1))
    lin = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)  # sRGB decode
    return np.clip(lin, MIN_ALBEDO, 1.0).astype(np.float32)


def uniform_maps(size, base_color: Sequence[float], metallic: float, roughness: float) -> TruthMaps:
    """Constant maps of the given size."""
    h, w = _shape(size)
    return TruthMaps(
        base_color=np.broadcast_to(np.asarray(base_color, np.float32), (h, w, 3)).copy(),
        metallic=np.full((h, w, 1), metallic, np.float32),
        roughness=np.full((h, w, 1), roughness, np.float32),
    )


def textured_maps(
    size,
    rng: np.random.Generator,
    metal: str = "none",
    metal_color: Sequence[float] = GOLD,
    metal_coverage: float = 0.35,
    roughness_range: tuple[float, float] = (0.2, 0.8),
    patches: int = 8,
    with_scratches: bool = True,
) -> TruthMaps:
    """Textured ground truth: sharp-edged patches, smooth variation and scratches.

    - base colour: Voronoi patches of a random palette, modulated by +-25% fBm;
    - roughness: a ramp across the map plus per-patch offsets and fBm, scratches smoother;
    - metallic: ``"none"`` (all 0), ``"binary"`` (0/1 blobs, metal texels get `metal_color`),
      or ``"smooth"`` (fBm in [0, 1]).
    """
    h, w = _shape(size)
    labels = voronoi_labels((h, w), patches, rng)
    base = palette(patches, rng)[labels]
    base = base * (0.75 + 0.5 * fbm((h, w), rng, octaves=3, base_cells=4))[..., None]
    r_lo, r_hi = roughness_range
    rough = gradient((h, w), 0.0, 1.0, angle_deg=rng.uniform(0, 360))
    rough = 0.5 * rough + 0.3 * rng.random(patches)[labels] + 0.2 * fbm((h, w), rng, octaves=3, base_cells=8)
    rough = r_lo + (r_hi - r_lo) * rough
    if with_scratches:
        s = scratches((h, w), rng, count=max(4, h // 8))
        rough = rough * (1 - 0.5 * s)
    if metal == "none":
        met = np.zeros((h, w))
    elif metal == "binary":
        mask = binary_mask((h, w), rng, coverage=metal_coverage)
        met = mask.astype(np.float64)
        base = np.where(mask[..., None], np.asarray(metal_color, np.float32), base)
    elif metal == "smooth":
        met = fbm((h, w), rng, octaves=2, base_cells=3)
    else:
        raise ValueError(f"metal must be 'none', 'binary' or 'smooth', got {metal!r}")
    return TruthMaps(
        base_color=np.clip(base, MIN_ALBEDO, 1.0).astype(np.float32),
        metallic=np.clip(met, 0.0, 1.0).astype(np.float32)[..., None],
        roughness=np.clip(rough, MIN_TRUTH_ROUGHNESS, 1.0).astype(np.float32)[..., None],
    )


def paste_tile(maps: TruthMaps, tile: TruthMaps, row: int, col: int) -> TruthMaps:
    """`maps` with `tile` written at tile index (row, col) of a grid of tile-sized cells."""
    th, tw = tile.shape
    r0, c0 = row * th, col * tw
    out = {}
    for name in ("base_color", "metallic", "roughness"):
        a = getattr(maps, name).copy()
        a[r0 : r0 + th, c0 : c0 + tw] = getattr(tile, name)
        out[name] = a
    return TruthMaps(**out)


def chart_maps(
    metallic_values: Sequence[float],
    roughness_values: Sequence[float],
    tile: int = 8,
    base_color: Sequence[float] = (0.8, 0.3, 0.1),
    metal_color: Optional[Sequence[float]] = None,
) -> TruthMaps:
    """The metallic x roughness chart: row r has `metallic_values[r]`, column c `roughness_values[c]`.

    Each cell is a uniform `tile` x `tile` block, so cell (r, c) covers uv in
    [c/C, (c+1)/C] x [r/R, (r+1)/R] (glTF orientation: row 0 at v = 0). With `metal_color`,
    the base colour blends towards it with metallic.
    """
    rows, cols = len(metallic_values), len(roughness_values)
    maps = uniform_maps((rows * tile, cols * tile), base_color, 0.0, 0.5)
    for r, m in enumerate(metallic_values):
        for c, rough in enumerate(roughness_values):
            color = np.asarray(base_color, np.float64)
            if metal_color is not None:
                color = (1 - m) * color + m * np.asarray(metal_color, np.float64)
            maps = paste_tile(maps, uniform_maps(tile, color, m, rough), r, c)
    return maps
