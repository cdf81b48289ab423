"""Material folders: a material's maps in the capture spec's fit-output layout (base_color.exr/.png,
metallic.exr, roughness.exr, metallic_roughness.png with G = roughness and B = metallic,
normal.png; occlusion.exr and emissive.exr), written (`write_material`) and read back
(`read_material`, `read_map`). Textures are in glTF orientation (row 0 is v = 0)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import CaptureError
from .atomic import make_folder
from .images import ImageInfo, read_image, srgb_decoded, srgb_encoded, write_image
from ..physics.material import Material

__all__ = ["MATERIAL_FILES", "write_material", "read_material", "read_map", "map_array", "pack_orm", "encode_normal"]

#: files of a material folder (fit-output layout)
MATERIAL_FILES = (
    "base_color.exr",
    "base_color.png",
    "metallic.exr",
    "roughness.exr",
    "metallic_roughness.png",
    "normal.png",
    "occlusion.exr",
    "emissive.exr",
)



def map_array(x) -> Optional[np.ndarray]:
    """A map as a float32 numpy array (None stays None)."""
    return None if x is None else np.asarray(x, dtype=np.float32)


def pack_orm(material) -> np.ndarray:
    """glTF packing: R = occlusion (1 when absent), G = roughness, B = metallic (linear)."""
    metallic = map_array(material.metallic)
    roughness = map_array(material.roughness)
    if metallic.shape[:2] != roughness.shape[:2]:
        raise ValueError(
            f"metallic {metallic.shape[:2]} and roughness {roughness.shape[:2]} maps differ in size; "
            "metallic_roughness.png packs them together"
        )
    occlusion = map_array(material.occlusion)
    if occlusion is None or occlusion.shape[:2] != metallic.shape[:2]:
        r = np.ones_like(metallic[..., :1])
    else:
        r = occlusion[..., :1]
    return np.concatenate([r, roughness[..., :1], metallic[..., :1]], axis=-1)


def encode_normal(normal: np.ndarray) -> np.ndarray:
    return np.clip(normal * 0.5 + 0.5, 0.0, 1.0)


def _decode_normal(encoded: np.ndarray) -> np.ndarray:
    n = encoded[..., :3] * 2.0 - 1.0
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    up = np.zeros_like(n)
    up[..., 2] = 1.0
    return np.where(norm > 0, n / np.where(norm > 0, norm, 1.0), up).astype(np.float32)


def write_material(directory: str | os.PathLike, material) -> list[Path]:
    """Write ``material`` to ``directory`` in the fit-output layout; return the files written.

    Always: ``base_color.exr`` (linear RGB float32), ``base_color.png`` (sRGB 8-bit),
    ``metallic.exr`` and ``roughness.exr`` (one channel float32), ``metallic_roughness.png``
    (glTF packing, linear 8-bit: R = occlusion or 1, G = roughness, B = metallic). When present:
    ``normal.png`` (tangent space, +Y, ``n * 0.5 + 0.5`` in 8 bits), ``occlusion.exr`` and
    ``emissive.exr`` (linear float32). Each file is written atomically, and an optional map's
    file the material lacks is removed, so that the folder reads back (`read_material`) as this
    material. Values a material folder may not hold (NaN, outside [0, 1]; emissive outside
    [0, inf)), empty maps, metallic and roughness maps of different sizes and a ``directory``
    that is a file are refused with `CaptureError` before anything is written.
    """
    directory = Path(directory)
    base, metallic, roughness = (map_array(m) for m in (material.base_color, material.metallic, material.roughness))
    normal, occlusion, emissive = (map_array(getattr(material, name, None)) for name in ("normal", "occlusion",
                                                                                         "emissive"))
    for name, values, top in (("base_color", base, 1.0), ("metallic", metallic, 1.0), ("roughness", roughness, 1.0),
                              ("occlusion", occlusion, 1.0), ("normal", normal, None), ("emissive", emissive, None)):
        if values is None:
            continue
        if values.ndim != 3 or values.size == 0:
            raise CaptureError(f"{directory}: the {name} map must be (H, W, C) with H, W >= 1, got shape {values.shape}")
        if name != "normal":
            _checked_map(values, directory, name, top)
        elif not np.all(np.isfinite(values)):  # unit vectors: any sign
            raise CaptureError(f"{directory}: the normal map holds NaN or inf values")
    if metallic.shape[:2] != roughness.shape[:2]:
        raise CaptureError(f"{directory}: the metallic {metallic.shape[:2]} and roughness {roughness.shape[:2]} maps "
                           "differ in size; metallic_roughness.png packs them together")
    if directory.exists() and not directory.is_dir():
        raise CaptureError(f"{directory}: is not a folder")
    orm = pack_orm(material)  # every check first: nothing is written for a material that is refused
    make_folder(directory)
    written = [
        write_image(directory / "base_color.exr", base, "float"),
        write_image(directory / "base_color.png", srgb_encoded(base), "uint8"),
        write_image(directory / "metallic.exr", metallic[..., :1], "float"),
        write_image(directory / "roughness.exr", roughness[..., :1], "float"),
        write_image(directory / "metallic_roughness.png", orm, "uint8", color_space="linear"),
    ]
    if normal is not None:
        written.append(write_image(directory / "normal.png", encode_normal(normal), "uint8", color_space="linear"))
    if occlusion is not None:
        written.append(write_image(directory / "occlusion.exr", occlusion[..., :1], "float"))
    if emissive is not None:
        written.append(write_image(directory / "emissive.exr", emissive, "float"))
    for name, values in (("normal.png", normal), ("occlusion.exr", occlusion), ("emissive.exr", emissive)):
        if values is None:
            (directory / name).unlink(missing_ok=True)  # an earlier material's map would read back as this one's
    return written


def _channels(pixels: np.ndarray, n: int, path: Path) -> np.ndarray:
    if pixels.shape[-1] < n:
        if pixels.shape[-1] == 1:
            return np.repeat(pixels, n, axis=-1)
        raise CaptureError(f"{path}: expected {n} channels, found {pixels.shape[-1]}")
    return pixels[..., :n]


def read_map(directory: str | os.PathLike, name: str) -> np.ndarray:
    """One map of a material folder: ``base_color`` (H, W, 3, linear), ``metallic`` or
    ``roughness`` (H, W, 1), from its EXR when present, else from the 8-bit PNG that holds it
    (``base_color.png`` sRGB-decoded; metallic from B and roughness from G of
    ``metallic_roughness.png``). Raises `CaptureError` naming the folder and the files tried,
    or the file when it holds NaN, inf or values outside [0, 1] (or is a cropped OpenEXR)."""
    if name not in ("base_color", "metallic", "roughness"):
        raise ValueError(f"unknown map {name!r}")
    directory = Path(directory)
    if not directory.is_dir():
        what = "is a file, not a material folder" if directory.exists() else "material folder not found"
        raise CaptureError(f"{directory}: {what}")
    exr, png = directory / f"{name}.exr", directory / ("base_color.png" if name == "base_color" else "metallic_roughness.png")
    if exr.is_file():
        pixels, info = _read_whole_exr(exr)
        if name != "base_color":  # one channel; a grey RGB(A) one holds it in each colour channel alike
            colour = [c for c in range(pixels.shape[-1]) if c != info.alpha_channel][:3]
            colours = pixels[..., colour]
            if len(colour) > 1 and not np.array_equal(colours, np.broadcast_to(colours[..., :1], colours.shape)):
                raise CaptureError(f"{exr}: {name} must be one channel; found {pixels.shape[-1]} channels that "
                                   "differ (channels " + ", ".join(info.channel_names) + ")")
        values, source = (_channels(pixels, 3, exr) if name == "base_color" else pixels[..., :1]), exr
    elif png.is_file():
        pixels = _channels(read_image(png)[0], 3, png)
        if name == "base_color":
            values = srgb_decoded(pixels)
        else:
            values = pixels[..., 2:3] if name == "metallic" else pixels[..., 1:2]
        source = png
    else:
        raise CaptureError(f"{directory}: material folder has no {exr.name} or {png.name}")
    return _checked_map(values, source, name)


def _read_whole_exr(path: Path) -> tuple[np.ndarray, ImageInfo]:
    """A material map's OpenEXR pixels and info; a cropped one (data window inside the display
    window) is refused."""
    pixels, info = read_image(path)
    if info.data_window is not None:
        raise CaptureError(f"{path}: the data window does not fill the display window (a cropped OpenEXR); "
                           "write the whole texture")
    return pixels, info


def _checked_map(values: np.ndarray, source: Path, name: str, top: Optional[float] = 1.0) -> np.ndarray:
    """``values`` of map ``name`` read from ``source``, refused when any is NaN or inf or lies
    outside [0, top] (no upper bound when ``top`` is None)."""
    bad = ~np.isfinite(values)
    if bad.any():
        raise CaptureError(f"{source}: {int(bad.any(-1).sum())} texels of {name} hold NaN or inf values")
    if values.min() < 0.0 or (top is not None and values.max() > top):
        span = "[0, inf)" if top is None else f"[0, {top:g}]"
        raise CaptureError(f"{source}: {name} must lie in {span}, found values from {values.min():g} to {values.max():g}")
    return values


def read_material(directory: str | os.PathLike):
    """Read a material folder (fit-output layout) as a `pbrfit.physics.material.Material`.

    The float EXR files are preferred (exact); without them the 8-bit PNGs are used
    (``base_color.png`` sRGB-decoded; metallic from B and roughness from G of
    ``metallic_roughness.png``). ``normal.png``, ``occlusion.exr`` and ``emissive.exr`` are
    optional. Raises `CaptureError` naming the folder when a required map is missing.
    """

    directory = Path(directory)
    base, metallic, roughness = (read_map(directory, name) for name in ("base_color", "metallic", "roughness"))

    def has(name: str) -> bool:
        return (directory / name).is_file()

    normal = _decode_normal(_channels(read_image(directory / "normal.png")[0], 3, directory / "normal.png")) if has("normal.png") else None
    occlusion = emissive = None
    if has("occlusion.exr"):
        path = directory / "occlusion.exr"
        occlusion = _checked_map(_read_whole_exr(path)[0][..., :1], path, "occlusion")
    if has("emissive.exr"):  # linear radiance: no upper bound
        path = directory / "emissive.exr"
        emissive = _checked_map(_channels(_read_whole_exr(path)[0], 3, path), path, "emissive", top=None)
    return Material(
        base_color=base, metallic=metallic, roughness=roughness,
        normal=normal, occlusion=occlusion, emissive=emissive,
    )  # fmt: skip
