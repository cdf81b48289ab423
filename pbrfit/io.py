"""Files: images through OpenImageIO, atomic writes, material folders and glTF export.

Conventions held here:

* Images in memory are float32 (H, W, C), row 0 at the top, values as stored in the file
  (an 8/16-bit file maps its codes to [0, 1]; no color transform, no alpha association:
  OpenImageIO is told ``oiio:UnassociatedAlpha`` both ways, so a PNG's color channels are
  returned and written exactly as stored, not multiplied or divided by alpha).
* Every write is atomic: the file is written under a temporary name in the same folder and
  renamed into place (`atomic_path`); a folder can be built the same way (`atomic_dir`).
* OpenImageIO's Python ``write_image`` garbles a 2-D numpy array, so single-channel data always
  goes out as (H, W, 1).
* Material folders use the fit-output layout of the capture spec (base_color.exr/.png,
  metallic.exr, roughness.exr, metallic_roughness.png with G = roughness, B = metallic,
  normal.png); textures are in glTF orientation (row 0 is v = 0).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Callable, Iterator, Optional, Sequence

import numpy as np

from .errors import CaptureError

__all__ = [
    "ImageInfo",
    "atomic_path",
    "atomic_dir",
    "check_output_dir",
    "check_not_inside",
    "OUTPUT_MARKER",
    "read_image",
    "color_channels",
    "read_image_info",
    "write_image",
    "read_material",
    "read_map",
    "write_material",
    "write_gltf",
    "MATERIAL_FILES",
]

# pixel formats OpenImageIO reports for integer (low dynamic range) files, and their code maxima
_LDR_MAX = {"uint8": 255, "uint16": 65535, "uint32": 4294967295, "int8": 127, "int16": 32767}
_WRITE_DTYPES = {"float": np.float32, "half": np.float16, "uint8": np.uint8, "uint16": np.uint16}

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


def _oiio():
    import OpenImageIO as oiio

    return oiio


# --- atomic writes -----------------------------------------------------------------------------
def _process_umask() -> int:
    """The process's file-creation mask (read once, at import: setting it to read it is not
    thread-safe)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: Temporary files and folders (`tempfile`) are created private (0600, 0700); outputs get the
#: modes a plain open() or mkdir() would give them.
_UMASK = _process_umask()
_FILE_MODE = 0o666 & ~_UMASK
_DIR_MODE = 0o777 & ~_UMASK


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``final`` (same folder, same suffix); rename on success.

    The temporary name keeps ``final``'s suffix, so tools that pick a format by extension
    (OpenImageIO, trimesh) write the right one. The file gets the mode the umask gives a new
    file. If the body raises, the temporary file is deleted and ``final`` is left as it was.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".tmp{final.suffix}", dir=final.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, _FILE_MODE)
        os.replace(tmp_path, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


class CacheWarning(UserWarning):
    """A cache file could not be written; the command goes on without it."""


def write_cache_file(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> None:
    """Write a cache file atomically with ``write(f)`` on the open temporary file. A cache that
    cannot be written (a full disk, no permission, a path through a file) costs only a later
    run's time: a `CacheWarning` naming its folder (once per folder and reason), and nothing else."""
    path = Path(path)
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            write(f)
    except OSError as err:
        said = (str(path.parent), str(err.strerror or err))
        if said not in _CACHE_WARNED:
            _CACHE_WARNED.add(said)
            warnings.warn(f"cache folder {said[0]}: cannot write ({said[1]}); going on without it",
                          CacheWarning, stacklevel=2)


#: (cache folder, reason) pairs already warned of in this process.
_CACHE_WARNED: set = set()


#: The file every output folder of a pbrfit command holds (its content: the kind of output).
#: Only a folder holding it, with the same kind, or an empty one, is ever replaced.
OUTPUT_MARKER = ".pbrfit-output"
#: Kinds of output folder: a fit's maps and report, or a capture folder (`render`, `synth`).
OUTPUT_KINDS = {"fit": "pbrfit fit output", "capture": "capture folder written by pbrfit"}


def output_path(final_dir: str | os.PathLike) -> Path:
    """``final_dir`` as an absolute path. A symbolic link is followed to the folder it names
    (the output replaces that folder, and the link keeps pointing at it); a link to nothing is
    `CaptureError`."""
    path = Path(os.path.abspath(final_dir))
    if path.is_symlink():
        if not path.exists():
            raise CaptureError(f"{path}: is a link to {os.readlink(path)}, which does not exist; "
                               "choose another output folder")
        path = Path(os.path.realpath(path))
    return path


def check_output_dir(final_dir: str | os.PathLike, kind: str) -> Path:
    """Refuse an output folder that writing would destroy; return it as an absolute path.

    `final_dir` may be missing, an empty folder, or a folder an earlier pbrfit command of the
    same `kind` (`OUTPUT_KINDS`) wrote, marked by `OUTPUT_MARKER`; that one is replaced, unless
    it holds files the command did not write (the marker lists them; a user's notes saved into
    an earlier output would go with it). A file, any other folder (a user's capture, photos,
    home), the current folder or one above it, and a place no folder can be made in (under a
    file, or without write permission) are `CaptureError`.
    """
    what = OUTPUT_KINDS[kind]
    final_dir = output_path(final_dir)
    cwd = Path.cwd()
    if final_dir == cwd or final_dir in cwd.parents:
        raise CaptureError(f"{final_dir}: is the current folder or holds it; choose another output folder")
    if final_dir.exists() and not final_dir.is_dir():
        raise CaptureError(f"{final_dir}: exists and is not a folder; choose another output folder")
    _check_creatable(final_dir)
    if final_dir.exists() and any(final_dir.iterdir()):
        marker = final_dir / OUTPUT_MARKER
        lines = marker.read_text(errors="replace").splitlines() if marker.is_file() else []
        if not lines or lines[0].strip() != kind:
            raise CaptureError(
                f"{final_dir}: exists and is not a {what} (no {OUTPUT_MARKER} of kind {kind!r}); "
                "refusing to replace it, choose another output folder or remove it"
            )
        if len(lines) > 1:  # the files it wrote (markers before the list name none)
            written = {line for line in lines[1:] if line}
            extra = sorted(p for p in _relative_files(final_dir) if p not in written and p != OUTPUT_MARKER)
            if extra:
                shown = ", ".join(extra[:3]) + (f" and {len(extra) - 3} more" if len(extra) > 3 else "")
                raise CaptureError(f"{final_dir}: holds files pbrfit did not write ({shown}); refusing to replace "
                                   "it, move them out or choose another output folder")
    return final_dir


def _relative_files(folder: Path) -> list[str]:
    """Every file under `folder`, as '/'-separated paths relative to it."""
    return [p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir()]


def _check_creatable(final_dir: Path) -> None:
    """`CaptureError` unless `final_dir`'s nearest existing ancestor is a folder this process
    may write in (the output is built beside `final_dir` and renamed into place)."""
    parent = final_dir.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise CaptureError(f"{final_dir}: {parent} is not a folder; choose another output folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CaptureError(f"{final_dir}: cannot write in {parent} (permission denied); choose another output folder")


def check_not_inside(folder: str | os.PathLike, out_dir: str | os.PathLike, role: str) -> None:
    """`CaptureError` when `folder` (an input: `role`) is `out_dir` or lies inside it, which
    replacing `out_dir` would delete: as written, and with links followed (`output_path`)."""
    folder_abs, out_abs = Path(os.path.abspath(folder)), Path(os.path.abspath(out_dir))
    for f, o in ((folder_abs, out_abs), (Path(os.path.realpath(folder)), Path(os.path.realpath(out_dir)))):
        if f == o or o in f.parents:
            raise CaptureError(f"{out_abs}: holds the {role} ({folder_abs}); choose another output folder")


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back meanwhile and handled on the way out, as their handlers would
    have (Ctrl-C's KeyboardInterrupt, `pbrfit.cli`'s SIGTERM, or the default action). Python runs
    signal handlers in the main thread whichever thread the signal reached, so their handlers are
    swapped for ones that only note the signal (a thread's signal mask would not do: another
    thread, a compile's or XLA's, takes a signal the main thread blocks). Elsewhere than in the
    main thread nothing is held."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(signum)
        if handler is not None:  # (None: a handler not set from Python, left as it is)
            previous[signum] = signal.signal(signum, lambda number, frame: caught.append(number))
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        for signum in caught:
            handler = previous[signum]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)


#: File-system refusals (a name too long, a full disk, no permission, a read-only place, a path
#: through a file or a loop of links, a failing device) that the command line reports in one line
#: with exit status 2, not as a bug.
REFUSED_ERRNOS = frozenset(getattr(errno, name) for name in (
    "ENAMETOOLONG", "ENOSPC", "EDQUOT", "EROFS", "EACCES", "EPERM", "EIO", "EFBIG", "ENOTDIR", "ELOOP")
    if hasattr(errno, name))


@contextlib.contextmanager
def atomic_dir(final_dir: str | os.PathLike, overwrite: bool = True, kind: Optional[str] = None) -> Iterator[Path]:
    """Yield a temporary folder beside ``final_dir``; rename it to ``final_dir`` on success.

    The folder gets the mode the umask gives a new folder. If the body raises, the temporary
    folder is removed and nothing appears at ``final_dir``.
    An existing ``final_dir`` is replaced when ``overwrite`` (moved aside, the new folder
    renamed in, the old one deleted), else `CaptureError`. With a `kind` (`OUTPUT_KINDS`), only
    an empty folder or an earlier output of that kind is replaced (`check_output_dir`), and the
    new folder is marked as one (`OUTPUT_MARKER`).
    """
    final_dir = output_path(final_dir)
    if final_dir.exists() and not overwrite:
        raise CaptureError(f"{final_dir}: already exists")
    if kind is not None:
        check_output_dir(final_dir, kind)
    try:
        final_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final_dir.name}.", suffix=".tmp", dir=final_dir.parent))
    except OSError as err:
        raise CaptureError(f"{final_dir}: cannot create the output folder: {err.strerror or err}") from None
    try:
        yield tmp
        if kind is not None:  # the kind, then the files written (`check_output_dir`)
            (tmp / OUTPUT_MARKER).write_text("\n".join([kind] + sorted(_relative_files(tmp))) + "\n")
        os.chmod(tmp, _DIR_MODE)
        if final_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{final_dir.name}.", suffix=".old", dir=final_dir.parent))
            try:
                with _signals_held():  # Ctrl-C or a kill between the two renames would lose both folders
                    os.replace(final_dir, old / "d")
                    try:
                        os.replace(tmp, final_dir)
                    except BaseException:
                        os.replace(old / "d", final_dir)  # the earlier output goes back
                        raise
            finally:
                shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final_dir)
    except OSError as err:  # a full disk, say: named as it would have been in the output
        shutil.rmtree(tmp, ignore_errors=True)
        name = str(err.filename or "")
        if err.errno not in REFUSED_ERRNOS or (name and not name.startswith(str(tmp))):
            raise
        raise CaptureError(f"{final_dir}{name[len(str(tmp)):]}: cannot write: {err.strerror or err}; "
                           "nothing was written") from None
    except CaptureError as err:  # a file of the output named by its temporary path: named as in the output
        shutil.rmtree(tmp, ignore_errors=True)
        if str(tmp) not in str(err):
            raise
        raise CaptureError(str(err).replace(str(tmp), str(final_dir))) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# --- images ------------------------------------------------------------------------------------
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


def _first_line(message: str) -> str:
    lines = [ln.strip() for ln in str(message).splitlines() if ln.strip()]
    return lines[0] if lines else "unknown error"


def _unassociated_config():
    oiio = _oiio()
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
    import sys

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
    oiio = _oiio()
    prefix = f"{where}: " if where else ""
    if not path.is_file():
        raise CaptureError(f"{prefix}image file not found: {path}")
    printed = [] if printed is None else printed
    with _held_stderr(printed):
        inp = oiio.ImageInput.open(str(path), _unassociated_config())
    if inp is None:
        raise CaptureError(f"{prefix}cannot read image {path}: {_first_line(oiio.geterror() or ''.join(printed))}")
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
    oiio = _oiio()
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
                           f"{_first_line(error or oiio.geterror() or ''.join(printed))}")
    if error:  # pixels, but the decoder hit a fault (a truncated JPEG reads its missing rows as grey)
        raise CaptureError(f"{prefix}image {path} is damaged: {_first_line(error)}")
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
    oiio = _oiio()
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
            raise CaptureError(f"cannot write image {path}: {_first_line(oiio.geterror())}")
        try:
            if not out.open(str(tmp), spec):
                raise CaptureError(f"cannot write image {path}: {_first_line(out.geterror())}")
            if not out.write_image(data):
                raise CaptureError(f"cannot write image {path}: {_first_line(out.geterror())}")
        finally:
            out.close()
    return path


# --- material folders --------------------------------------------------------------------------
def _srgb_encode(x: np.ndarray) -> np.ndarray:
    from .color import linear_to_srgb_host

    return linear_to_srgb_host(np.clip(np.asarray(x, np.float32), 0.0, 1.0))


def _srgb_decode(x: np.ndarray) -> np.ndarray:
    from .color import srgb_to_linear_host

    return srgb_to_linear_host(x)


def _np(x) -> Optional[np.ndarray]:
    return None if x is None else np.asarray(x, dtype=np.float32)


def _pack_orm(material) -> np.ndarray:
    """glTF packing: R = occlusion (1 when absent), G = roughness, B = metallic (linear)."""
    metallic = _np(material.metallic)
    roughness = _np(material.roughness)
    if metallic.shape[:2] != roughness.shape[:2]:
        raise ValueError(
            f"metallic {metallic.shape[:2]} and roughness {roughness.shape[:2]} maps differ in size; "
            "metallic_roughness.png packs them together"
        )
    occlusion = _np(material.occlusion)
    if occlusion is None or occlusion.shape[:2] != metallic.shape[:2]:
        r = np.ones_like(metallic[..., :1])
    else:
        r = occlusion[..., :1]
    return np.concatenate([r, roughness[..., :1], metallic[..., :1]], axis=-1)


def _encode_normal(normal: np.ndarray) -> np.ndarray:
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
    base, metallic, roughness = _np(material.base_color), _np(material.metallic), _np(material.roughness)
    normal, occlusion, emissive = (_np(getattr(material, name, None)) for name in ("normal", "occlusion", "emissive"))
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
    orm = _pack_orm(material)  # every check first: nothing is written for a material that is refused
    directory.mkdir(parents=True, exist_ok=True)
    written = [
        write_image(directory / "base_color.exr", base, "float"),
        write_image(directory / "base_color.png", _srgb_encode(base), "uint8"),
        write_image(directory / "metallic.exr", metallic[..., :1], "float"),
        write_image(directory / "roughness.exr", roughness[..., :1], "float"),
        write_image(directory / "metallic_roughness.png", orm, "uint8", color_space="linear"),
    ]
    if normal is not None:
        written.append(write_image(directory / "normal.png", _encode_normal(normal), "uint8", color_space="linear"))
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
        raise CaptureError(f"material folder not found: {directory}")
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
            values = _srgb_decode(pixels)
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
    """Read a material folder (fit-output layout) as a `pbrfit.material.Material`.

    The float EXR files are preferred (exact); without them the 8-bit PNGs are used
    (``base_color.png`` sRGB-decoded; metallic from B and roughness from G of
    ``metallic_roughness.png``). ``normal.png``, ``occlusion.exr`` and ``emissive.exr`` are
    optional. Raises `CaptureError` naming the folder when a required map is missing.
    """
    from .material import Material

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


# --- glTF export -------------------------------------------------------------------------------
def _pil_image(pixels: np.ndarray):
    """8-bit PIL image from [0, 1] floats, row 0 at the top (glTF: row 0 is v = 0)."""
    from PIL import Image

    codes = np.round(np.clip(np.asarray(pixels, np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)
    if codes.shape[-1] == 1:
        return Image.fromarray(codes[..., 0], mode="L")
    return Image.fromarray(np.ascontiguousarray(codes[..., :3]), mode="RGB")


def _is_uniform(material) -> bool:
    """Whether glTF's factors hold ``material`` whole: it reads no texture coordinates
    (`needs_texture_coordinates`) and has no occlusion map, for which glTF has no factor."""
    return not needs_texture_coordinates(material) and getattr(material, "occlusion", None) is None


def needs_texture_coordinates(material) -> bool:
    """Whether rendering ``material`` reads texture coordinates: any map larger than 1 x 1
    (occlusion and emissive included), or a normal map."""
    maps = [_np(getattr(material, name, None)) for name in ("base_color", "metallic", "roughness", "occlusion",
                                                            "emissive")]
    return getattr(material, "normal", None) is not None or any(m is not None and m.shape[:2] != (1, 1) for m in maps)


def _glb_with_json(data: bytes, edit) -> bytes:
    """A GLB whose JSON chunk is ``edit(json)``: header, JSON chunk (space-padded to 4 bytes),
    then the other chunks unchanged (glTF 2.0, "GLB File Format Specification")."""
    import json
    import struct

    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    if magic != b"glTF" or json_type != b"JSON":
        raise ValueError("not a GLB with a leading JSON chunk")
    tree = edit(json.loads(data[20 : 20 + json_len]))
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    rest = data[20 + json_len :]
    chunk = struct.pack("<I4s", len(text), b"JSON") + text
    return struct.pack("<4sII", magic, version, 12 + len(chunk) + len(rest)) + chunk + rest


def _export_glb(path, mesh, visual, edit=None) -> Path:
    """``mesh``'s vertices, faces and vertex normals with ``visual``, as a GLB at ``path``
    (atomically); ``edit`` may rewrite the glTF JSON first (`_glb_with_json`)."""
    import trimesh

    out_mesh = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices),
        faces=np.asarray(mesh.faces),
        vertex_normals=np.asarray(mesh.vertex_normals),
        visual=visual,
        process=False,
    )
    data = out_mesh.export(file_type="glb", include_normals=True)
    if edit is not None:
        data = _glb_with_json(data, edit)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def _write_uniform_gltf(path: Path, mesh, material) -> Path:
    from trimesh.visual.material import PBRMaterial
    from trimesh.visual.texture import TextureVisuals

    base = [float(v) for v in np.clip(_np(material.base_color).reshape(-1)[:3], 0.0, 1.0)] + [1.0]
    metallic = float(np.clip(_np(material.metallic).reshape(-1)[0], 0.0, 1.0))
    roughness = float(np.clip(_np(material.roughness).reshape(-1)[0], 0.0, 1.0))
    emissive = _np(getattr(material, "emissive", None))

    def exact_factors(tree):  # trimesh stores baseColorFactor as 8-bit; write the floats
        for m in tree.get("materials", []):
            m["pbrMetallicRoughness"] = dict(baseColorFactor=base, metallicFactor=metallic, roughnessFactor=roughness)
            if emissive is not None:  # clipped to [0, 1], as the emissive texture is
                m["emissiveFactor"] = [float(v) for v in np.clip(emissive.reshape(-1)[:3], 0.0, 1.0)]
        return tree

    return _export_glb(path, mesh, TextureVisuals(material=PBRMaterial(name="pbrfit", doubleSided=True)), exact_factors)


def write_gltf(path: str | os.PathLike, mesh, material) -> Path:
    """Write ``mesh`` with ``material`` as a binary glTF (GLB) at ``path``, atomically.

    ``mesh`` is a `trimesh.Trimesh` whose ``visual.uv`` is in glTF orientation (v = 0 at the
    top row of the texture), as `pbrfit.scene.load_capture` gives it. trimesh's exporter
    expects its own convention (v = 0 at the bottom) and writes TEXCOORD_0 = (u, 1 - v), so the
    uv is flipped before export and TEXCOORD_0 ends up equal to ``mesh.visual.uv``. Textures are
    stored with row 0 at the top of the image, so texel row 0 is v = 0 as glTF requires. baseColorTexture is sRGB 8-bit,
    metallicRoughnessTexture linear (R = occlusion or 1, G = roughness, B = metallic) with
    factors 1; normalTexture, occlusionTexture (the same image's R, or an image of its own when its
    size differs from metallic and roughness) and emissiveTexture
    (factor 1, clipped to [0, 1]) when the material has them. Vertex normals are written
    (NORMAL), so shading matches the mesh the material was fitted on.

    A uniform material (1 x 1 maps, emissive included; no normal or occlusion map) is written as
    glTF factors instead, exactly (baseColorFactor is linear, as the fit's base color): no
    textures, and no texture coordinates needed. A material of 1 x 1 maps with a 1 x 1 occlusion
    map, which only a texture can hold, is written with textures and TEXCOORD_0 = (0, 0) on a
    mesh without texture coordinates: a 1 x 1 texture reads the same everywhere.
    """
    from trimesh.visual.material import PBRMaterial
    from trimesh.visual.texture import TextureVisuals

    if _is_uniform(material):
        return _write_uniform_gltf(Path(path), mesh, material)
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        if needs_texture_coordinates(material):
            raise ValueError("write_gltf needs a mesh with one texture coordinate per vertex (mesh.visual.uv)")
        uv = np.zeros((len(mesh.vertices), 2))
    base = _np(material.base_color)
    orm = _pack_orm(material)
    orm_image = _pil_image(orm)
    kwargs = dict(
        baseColorTexture=_pil_image(_srgb_encode(base)),
        metallicRoughnessTexture=orm_image,
        metallicFactor=1.0,
        roughnessFactor=1.0,
        baseColorFactor=[255, 255, 255, 255],
        name="pbrfit",
        doubleSided=True,  # pbrfit shades both sides of a face (`pbrfit.gbuffer`)
    )
    normal = _np(getattr(material, "normal", None))
    if normal is not None:
        kwargs["normalTexture"] = _pil_image(_encode_normal(normal))
    occlusion = _np(getattr(material, "occlusion", None))
    if occlusion is not None:
        if occlusion.shape[:2] == orm.shape[:2]:
            kwargs["occlusionTexture"] = orm_image  # its R channel, as glTF reads occlusion
        else:  # a size of its own: its own image (R, repeated so viewers show grey)
            kwargs["occlusionTexture"] = _pil_image(np.repeat(occlusion[..., :1], 3, axis=-1))
    emissive = _np(getattr(material, "emissive", None))
    if emissive is not None:
        kwargs["emissiveTexture"] = _pil_image(_srgb_encode(emissive))
        kwargs["emissiveFactor"] = [1.0, 1.0, 1.0]
    uv = np.asarray(uv, dtype=np.float64)[:, :2]
    uv_trimesh = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])  # undone by trimesh's exporter
    return _export_glb(path, mesh, TextureVisuals(uv=uv_trimesh, material=PBRMaterial(**kwargs)))
