"""Images through OpenImageIO: reading, with what the file says about itself (`ImageInfo`), and
atomic writing.

Conventions held here:

* Images in memory are float32 (H, W, C), row 0 at the top, values as stored in the file
  (an 8/16-bit file maps its codes to [0, 1]; no color transform, no alpha association:
  OpenImageIO is told ``oiio:UnassociatedAlpha`` both ways, so a PNG's color channels are
  returned and written exactly as stored, not multiplied or divided by alpha).
* Every write is atomic (`pbrfit.io.atomic.atomic_path`).
* OpenImageIO's Python ``write_image`` garbles a 2-D numpy array, so single-channel data always
  goes out as (H, W, 1).

Material folders are `pbrfit.io.material_files`, glTF export `pbrfit.io.gltf_export`, atomic writes
and output folders `pbrfit.io.atomic`.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np
import OpenImageIO as oiio

from .atomic import atomic_path
from ..errors import CaptureError, first_line
from ..physics.color import linear_to_srgb_host, srgb_to_linear_host

__all__ = ["ImageInfo", "read_image", "color_channels", "read_image_info", "data_window_mask", "write_image",
           "srgb_encoded", "srgb_decoded"]

# pixel formats OpenImageIO reports for integer (low dynamic range) files, and their code maxima
_LDR_MAX = {"uint8": 255, "uint16": 65535, "uint32": 4294967295, "int8": 127, "int16": 32767}
_WRITE_DTYPES = {"float": np.float32, "half": np.float16, "uint8": np.uint8, "uint16": np.uint16}



@dataclass(frozen=True)
class ImageInfo:
    """What `read_image` learnt about a file.

    Attributes:
        path: the file.
        width, height, channels: the image size.
        channel_names: as stored (e.g. ``("R", "G", "B", "A")``).
        format: pixel format as stored: ``"uint8"``, ``"uint16"``, ``"half"``, ``"float"``, ...
        bits: bits per channel.
        is_ldr: integer pixels (a code maximum exists, values lie in [0, 1] once read).
        alpha_channel: index of the alpha channel, or None (for a layered OpenEXR read through
            one of its layers, `color_channels`, that layer's ``.A``).
        associated_alpha: the color channels are premultiplied by alpha as stored: always for
            OpenEXR, for TIFF unless the file says unassociated; PNG, BMP, TGA... are straight.
        file_format: OpenImageIO's format name (``"png"``, ``"openexr"``, ``"hdr"``, ``"tiff"``, ``"jpeg"``).
        data_window: for an OpenEXR whose data window differs from its display window (a crop or
            overscan), the display-window pixels that hold data, ``(x0, y0, x1, y1)`` (end
            exclusive); `read_image` returns the display window, 0 elsewhere. None otherwise.
    """

    path: Path
    width: int
    height: int
    channels: int
    channel_names: tuple[str, ...]
    format: str
    bits: int
    is_ldr: bool
    alpha_channel: Optional[int]
    file_format: str
    associated_alpha: bool = False
    data_window: Optional[tuple[int, int, int, int]] = None


def _unassociated_config():
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    return config


def _windows(spec, file_format: str):
    """(data window, display window) as (x, y, width, height), or None when they agree or the
    file is not an OpenEXR (only OpenEXR's display window is the camera's frame: PNG's oFFs
    offset or TIFF's position say where an image sits on a page, not a crop of it)."""
    if str(file_format) != "openexr":
        return None
    data = (int(spec.x), int(spec.y), int(spec.width), int(spec.height))
    display = (int(spec.full_x), int(spec.full_y), int(spec.full_width), int(spec.full_height))
    if data == display or display[2] <= 0 or display[3] <= 0:
        return None
    return data, display


def _color_layer(names) -> tuple[Optional[str], list[str]]:
    """(the colour layer an image is read through, every colour layer), by channel name: "" for
    plain R, G, B; else the one prefix p with p.R, p.G and p.B, or of several the one whose last
    part is "Combined" (Blender's multilayer OpenEXR: "ViewLayer.Combined.R" beside
    "ViewLayer.AO.R", ...). None where no channel is so named, or the layers leave it open."""
    index = set(names)
    if "Y" in index and not {"R", "G", "B"} <= index:  # a grey image (beside other layers): Y
        return None, []
    layers = [""] if {"R", "G", "B"} <= index else []
    layers += [n[:-2] for n in names if n.endswith(".R") and {n[:-2] + ".G", n[:-2] + ".B"} <= index]
    if "" in layers or len(layers) == 1:
        return layers[0], layers
    beauty = [layer for layer in layers if layer.rsplit(".", 1)[-1].lower() == "combined"]
    return (beauty[0] if len(beauty) == 1 else None), layers


def color_channels(info: ImageInfo, where: str) -> list[int]:
    """The indices of an image's colour channels (three, or one for grey): R, G, B by name
    (`_color_layer`), Y for a grey image, else the channels in stored order less alpha. Raises
    `CaptureError` when several colour layers leave open which one holds the image, for CIE
    X, Y, Z channels, and for an OpenEXR of several channels none of which is R, G, B or Y (a
    normal or position pass; one channel of any name is a grey image)."""
    names = list(info.channel_names)
    layer, layers = _color_layer(names)
    if layer is not None:
        return [names.index(f"{layer}.{c}" if layer else c) for c in "RGB"]
    if {"X", "Y", "Z"} <= set(names):
        raise CaptureError(f"{where}: image {info.path} holds CIE X, Y, Z channels; pbrfit reads R, G, B (or grey Y)")
    if "Y" in names:
        return [names.index("Y")]
    if layers:
        raise CaptureError(f"{where}: image {info.path} holds several colour layers ({', '.join(layers)}) and no "
                           "R, G, B channels; pbrfit reads R, G, B, a single layer, or a 'Combined' one")
    if str(info.file_format) == "openexr" and len(names) > 1 \
            and not any(n.rsplit(".", 1)[-1] in ("R", "G", "B") for n in names):
        # OpenEXR names what each channel holds: depth (Z), normals (N.X), ids are no image
        raise CaptureError(f"{where}: image {info.path} holds no colour channels (R, G, B or Y), only "
                           f"{', '.join(names[:6])}{' ...' if len(names) > 6 else ''}")
    # (a lone channel that a reader calls alpha is still the image)
    return [c for c in range(info.channels) if c != info.alpha_channel][:3] or [0]


def _info(path: Path, spec, file_format: str) -> ImageInfo:
    fmt = str(spec.format)
    alpha = int(spec.alpha_channel) if spec.alpha_channel >= 0 else None
    layer, _ = _color_layer(tuple(spec.channelnames))
    if layer:  # read through a layer: its own alpha, else a plain A, else none
        names = list(spec.channelnames)
        alpha = next((names.index(a) for a in (f"{layer}.A", "A") if a in names), None)
    windows = _windows(spec, file_format)
    data_window = None
    if windows is not None:
        (x, y, w, h), (fx, fy, fw, fh) = windows
        x0, y0 = min(max(x - fx, 0), fw), min(max(y - fy, 0), fh)
        data_window = (x0, y0, max(min(x + w - fx, fw), x0), max(min(y + h - fy, fh), y0))
    return ImageInfo(
        path=path,
        width=int(spec.full_width) if windows else int(spec.width),
        height=int(spec.full_height) if windows else int(spec.height),
        channels=int(spec.nchannels),
        channel_names=tuple(spec.channelnames),
        format=fmt,
        bits=int(spec.format.size()) * 8,
        is_ldr=fmt in _LDR_MAX,
        alpha_channel=alpha,
        file_format=str(file_format),
        associated_alpha=alpha is not None and (
            str(file_format) == "openexr"
            or (str(file_format) == "tiff" and spec.get_int_attribute("oiio:UnassociatedAlpha", 0) != 1)
        ),
        data_window=data_window,
    )


@contextlib.contextmanager
def _held_stderr(sink: list) -> Iterator[None]:
    """Hold what C libraries write to the process's standard error (file descriptor 2) meanwhile,
    and append it to `sink`: libpng prints "libpng error: ..." itself before OpenImageIO reports
    the failure, which pbrfit words as one line of its own. Where standard error has no file
    descriptor (a test's capture), nothing is held."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), fd)
        try:
            yield
        finally:
            os.dup2(saved, fd)
            os.close(saved)
            held.seek(0)
            sink.append(held.read().decode("utf-8", "replace"))


def _open_image(path: Path, where: str | None, printed: Optional[list] = None):
    """An open OpenImageIO ImageInput (alpha unassociated), or `CaptureError` naming the file."""
    prefix = f"{where}: " if where else ""
    if not path.is_file():
        raise CaptureError(f"{prefix}image file not found: {path}")
    printed = [] if printed is None else printed
    with _held_stderr(printed):
        inp = oiio.ImageInput.open(str(path), _unassociated_config())
    if inp is None:
        raise CaptureError(f"{prefix}cannot read image {path}: {first_line(oiio.geterror() or ''.join(printed))}")
    return inp


def read_image_info(path: str | os.PathLike, where: str | None = None) -> ImageInfo:
    """The `ImageInfo` of an image file, reading its header only (raises like `read_image`)."""
    path = Path(path)
    inp = _open_image(path, where)
    try:
        return _info(path, inp.spec(), inp.format_name())
    finally:
        inp.close()


def read_image(path: str | os.PathLike, where: str | None = None) -> tuple[np.ndarray, ImageInfo]:
    """Read an image file as float32 (H, W, C) pixels and its `ImageInfo`.

    Integer files map codes to [0, 1] (code / max); float files are returned as stored; no
    color conversion happens here. Raises `CaptureError` (prefixed with ``where`` when given)
    when the file is missing or OpenImageIO cannot read it, or reads it but reports a fault (a
    truncated JPEG).
    """
    path = Path(path)
    prefix = f"{where}: " if where else ""
    printed = []  # what the format's library printed itself (libpng: "libpng error: ...")
    inp = _open_image(path, where, printed)
    try:
        spec = inp.spec()
        with _held_stderr(printed):
            pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        error = inp.geterror()
        file_format = inp.format_name()
    finally:
        inp.close()
    if pixels is None or not isinstance(pixels, np.ndarray) or pixels.size == 0:
        raise CaptureError(f"{prefix}cannot read image {path}: "
                           f"{first_line(error or oiio.geterror() or ''.join(printed))}")
    if error:  # pixels, but the decoder hit a fault (a truncated JPEG reads its missing rows as grey)
        raise CaptureError(f"{prefix}image {path} is damaged: {first_line(error)}")
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    elif pixels.ndim == 4:  # volume images: take the first slice
        pixels = pixels[0]
    info = _info(path, spec, file_format)
    windows = _windows(spec, file_format)
    if windows is not None:  # an OpenEXR crop or overscan: the display window is the image
        (x, y, _, _), (fx, fy, fw, fh) = windows
        x0, y0, x1, y1 = info.data_window
        out = np.zeros((fh, fw, pixels.shape[-1]), np.float32)
        out[y0:y1, x0:x1] = pixels[y0 + fy - y : y1 + fy - y, x0 + fx - x : x1 + fx - x]
        pixels = out
    return pixels, info


def data_window_mask(info: ImageInfo) -> np.ndarray:
    """(H, W) bool: the pixels of `read_image`'s result that the file holds (all but where an
    OpenEXR's data window leaves its display window empty)."""
    if info.data_window is None:
        return np.ones((info.height, info.width), bool)
    x0, y0, x1, y1 = info.data_window
    mask = np.zeros((info.height, info.width), bool)
    mask[y0:y1, x0:x1] = True
    return mask


def write_image(
    path: str | os.PathLike,
    pixels: np.ndarray,
    dtype: str = "float",
    channel_names: Sequence[str] | None = None,
    color_space: str = "srgb",
) -> Path:
    """Write (H, W) or (H, W, C) pixels to ``path`` atomically; the format follows the suffix.

    ``dtype`` is the stored pixel type: ``"float"`` (float32), ``"half"``, ``"uint8"`` or
    ``"uint16"``; integer types clip to [0, 1] and round ``x * max``. A 2-D array is written as
    (H, W, 1) (OpenImageIO garbles 2-D arrays). A 4-channel image gets alpha in channel 3,
    stored unassociated (color values as given). ``color_space`` says what integer pixels hold,
    for the file's metadata: ``"srgb"`` (sRGB-encoded colour; a PNG gets sRGB, gAMA and cHRM
    chunks) or ``"linear"`` (linear values or data such as packed metallic/roughness, normals
    and masks; a PNG gets gAMA 1.0 and no sRGB chunk). Pixels are stored as given either way.
    """
    if color_space not in ("srgb", "linear"):
        raise ValueError(f"color_space must be 'srgb' or 'linear', got {color_space!r}")
    if dtype not in _WRITE_DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(_WRITE_DTYPES)}, got {dtype!r}")
    arr = np.asarray(pixels)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3:
        raise ValueError(f"pixels must be (H, W) or (H, W, C), got shape {arr.shape}")
    height, width, channels = arr.shape
    if dtype in ("uint8", "uint16"):
        code_max = _LDR_MAX[dtype]
        data = np.round(np.clip(np.nan_to_num(arr.astype(np.float64)), 0.0, 1.0) * code_max)
        data = data.astype(_WRITE_DTYPES[dtype])
    else:
        data = arr.astype(_WRITE_DTYPES[dtype])
    data = np.ascontiguousarray(data)
    spec = oiio.ImageSpec(width, height, channels, dtype)
    if channel_names is not None:
        if len(channel_names) != channels:
            raise ValueError(f"{len(channel_names)} channel names for {channels} channels")
        spec.channelnames = tuple(channel_names)
    if channels == 4:
        spec.alpha_channel = 3
    spec.attribute("oiio:UnassociatedAlpha", 1)
    spec.attribute("DateTime", "")  # no time stamp (EXR's capDate): the same pixels, the same bytes
    if dtype in ("uint8", "uint16"):  # the names every OpenImageIO's PNG writer knows
        spec.attribute("oiio:ColorSpace", "Linear" if color_space == "linear" else "sRGB")
    path = Path(path)
    if path.suffix.lower() in (".jpg", ".jpeg"):  # as close to the pixels as JPEG goes: OpenImageIO's
        # default halves the chroma resolution (4:2:0), 0.64 off at a red-blue edge, 0.004 at 4:4:4
        spec.attribute("Compression", "jpeg:100")
        spec.attribute("jpeg:subsampling", "4:4:4")
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise CaptureError(f"cannot write image {path}: {first_line(oiio.geterror())}")
        try:
            if not out.open(str(tmp), spec):
                raise CaptureError(f"cannot write image {path}: {first_line(out.geterror())}")
            if not out.write_image(data):
                raise CaptureError(f"cannot write image {path}: {first_line(out.geterror())}")
        finally:
            out.close()
    return path


def srgb_encoded(x: np.ndarray) -> np.ndarray:
    """Linear values clipped to [0, 1], sRGB-encoded (numpy: for 8- and 16-bit files)."""
    return linear_to_srgb_host(np.clip(np.asarray(x, np.float32), 0.0, 1.0))


def srgb_decoded(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values decoded to linear (numpy)."""
    return srgb_to_linear_host(x)
