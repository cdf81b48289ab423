"""Atomic writes and output folders: a file or a folder is written under a temporary name beside
its place and renamed into place (`atomic_path`, `atomic_dir`), so it appears whole or not at
all; an output folder replaces only an earlier output of the same kind (`check_output_dir`,
`OUTPUT_MARKER`); cache files that cannot be written only warn (`write_cache_file`). A process
ended by a signal removes every temporary not yet renamed into place (`abandon_writes`)."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import signal
import tempfile
import threading
import warnings
from pathlib import Path
from typing import BinaryIO, Callable, Iterator, Optional

from ..errors import CaptureError, listed

__all__ = ["atomic_path", "atomic_dir", "make_folder", "check_output_dir", "check_not_inside", "output_path", "write_cache_file",
           "abandon_writes", "hold_on_abandon", "CacheWarning", "atomic_open", "OUTPUT_MARKER", "OUTPUT_KINDS", "REFUSED_ERRNOS"]


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

#: How `atomic_open` opens `atomic_path`'s temporary: for writing, without making it.
_REWRITE = "r+b"
#: Every temporary file and folder the writers below have made and neither renamed into place nor
#: removed (insertion-ordered), for `abandon_writes`.
_TEMPORARIES: dict = {}
#: Held while a temporary is made and registered, and around each rename into place with its
#: unregistering; `abandon_writes` takes it and keeps it, so that no temporary is made and no output
#: appears after it (a rename between its cleanup and the process's end would leave a half output).
_RENAMING = threading.Lock()
#: Locks of other writers (JAX's compilation cache) that `abandon_writes` takes and keeps too, so
#: that the process does not end halfway through one of their files; by name (`hold_on_abandon`).
_HELD_ON_ABANDON: dict = {}
#: How many times `abandon_writes` removes a folder another thread may still be writing into.
_REMOVE_TRIES = 20


@contextlib.contextmanager
def _renaming():
    """`_RENAMING`, with SIGINT and SIGTERM held back until it is released (`_signals_held`): their
    handler (`abandon_writes`) runs in the main thread and would wait for the lock that thread
    holds, and a temporary made but not yet noted would be left behind."""
    with _signals_held(), _RENAMING:
        yield


def _new_temporary(make: Callable[[], str]) -> Path:
    """A temporary made by ``make`` (``tempfile.mkstemp``'s or ``mkdtemp``'s call) and noted for
    `abandon_writes`, under `_RENAMING` (`_renaming`)."""
    with _renaming():
        path = Path(make())
        _TEMPORARIES[path] = None
    return path


def make_folder(path: str | os.PathLike) -> None:
    """``path`` and its missing parents (``mkdir(parents=True, exist_ok=True)``), made under
    `_RENAMING` (`_renaming`), so that none is made once `abandon_writes` has begun: a writer in
    another thread would otherwise make a temporary folder it removed again (an output's, the
    file the writer is about to write inside it) and leave it behind."""
    with _renaming():
        Path(path).mkdir(parents=True, exist_ok=True)


def _into_place(tmp: Path, final: Path, folder: Optional[Path] = None) -> None:
    """Rename a temporary into place and forget it, under `_RENAMING` (`_renaming`); ``folder``:
    the temporary's own folder (`atomic_path`'s), the temporary noted, removed once empty."""
    with _renaming():
        os.replace(tmp, final)
        if folder is not None:
            os.rmdir(folder)
        _TEMPORARIES.pop(tmp if folder is None else folder, None)


def _discard(path: Path) -> None:
    """Remove a temporary file or folder, if still there, and forget it."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()
    _TEMPORARIES.pop(path, None)


def hold_on_abandon(name: str, lock) -> None:
    """Have `abandon_writes` take ``lock`` too (anything with ``acquire(timeout=seconds)``, such as
    a ``threading.Lock`` or a ``filelock.FileLock``) and keep it; ``name`` replaces an earlier lock
    of that name."""
    _HELD_ON_ABANDON[name] = lock


def abandon_writes(timeout: float) -> list[Path]:
    """For a process about to end at once (a signal): wait at most ``timeout`` seconds for each
    rename under way and each `hold_on_abandon` lock, keep them all, and remove every temporary
    the writers here have made and not renamed into place; return those. No output appears
    afterwards: a writer that reaches its rename waits for ever, so the process must end next
    (``os._exit``). A folder another thread is still writing into is removed again until it is gone."""
    _RENAMING.acquire(timeout=timeout)
    for lock in list(_HELD_ON_ABANDON.values()):
        with contextlib.suppress(Exception):  # not taken in time (or gone): the process ends anyway
            lock.acquire(timeout=timeout)
    removed = list(_TEMPORARIES)
    for path in reversed(removed):
        for _ in range(_REMOVE_TRIES):
            _discard(path)
            if not os.path.lexists(path):
                break
    _TEMPORARIES.clear()
    return removed


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path for ``final``: its name, in a private temporary folder beside it;
    rename it into place on success.

    The temporary keeps ``final``'s name, so tools that pick a format by extension (OpenImageIO,
    trimesh) write the right one. The file gets the mode the umask gives a new file. If the body
    raises, the temporary folder is deleted and ``final`` is left as it was. The temporary exists,
    empty, when yielded; a writer that writes to a file object takes `atomic_open` instead,
    which opens it without making it again. The folder is what `abandon_writes` removes: a writer
    that writes by path (OpenImageIO) and reaches its write after that cannot make the file
    again, as its folder is gone.
    """
    final = Path(final)
    make_folder(final.parent)

    def make() -> str:
        folder = tempfile.mkdtemp(prefix=f".{final.stem}.", suffix=".tmp", dir=final.parent)
        (Path(folder) / final.name).touch()
        return folder

    folder = _new_temporary(make)
    tmp_path = folder / final.name
    try:
        yield tmp_path
        os.chmod(tmp_path, _FILE_MODE)
        _into_place(tmp_path, final, folder)
    except BaseException:
        _discard(folder)
        raise


@contextlib.contextmanager
def atomic_open(final: str | os.PathLike) -> Iterator[BinaryIO]:
    """`atomic_path`'s temporary, opened for binary writing: renamed into place once the block
    and the file close. It is opened "r+b", which cannot make it again where a signal's
    `abandon_writes` removed it between its making and the open ("wb" would, and leave it
    behind): the write then fails, and the process is ending anyway."""
    with atomic_path(final) as tmp, open(tmp, _REWRITE) as f:
        yield f


class CacheWarning(UserWarning):
    """A cache file could not be written; the command goes on without it."""


def write_cache_file(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> None:
    """Write a cache file atomically with ``write(f)`` on the open temporary file. A cache that
    cannot be written (a full disk, no permission, a path through a file) costs only a later
    run's time: a `CacheWarning` naming its folder (once per folder and reason), and nothing else."""
    path = Path(path)
    try:
        with atomic_open(path) as f:
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
                raise CaptureError(f"{final_dir}: holds files pbrfit did not write ({listed(extra)}); refusing to replace "
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
    have (Ctrl-C's KeyboardInterrupt, `pbrfit.cli.main`'s SIGTERM, or the default action). Python runs
    signal handlers in the main thread whichever thread the signal reached, so their handlers are
    swapped for ones that only note the signal (a thread's signal mask would not do: another
    thread, a compile's or XLA's, takes a signal the main thread blocks). Elsewhere than in the
    main thread nothing is held."""
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
        make_folder(final_dir.parent)
        tmp = _new_temporary(lambda: tempfile.mkdtemp(prefix=f".{final_dir.name}.", suffix=".tmp",
                                                       dir=final_dir.parent))
    except OSError as err:
        raise CaptureError(f"{final_dir}: cannot create the output folder: {err.strerror or err}") from None
    try:
        yield tmp
        if kind is not None:  # the kind, then the files written (`check_output_dir`)
            (tmp / OUTPUT_MARKER).write_text("\n".join([kind] + sorted(_relative_files(tmp))) + "\n")
        os.chmod(tmp, _DIR_MODE)
        if final_dir.exists():
            old = _new_temporary(lambda: tempfile.mkdtemp(prefix=f".{final_dir.name}.", suffix=".old",
                                                          dir=final_dir.parent))
            try:
                # Ctrl-C or a kill between the two renames would lose both folders
                with _renaming():
                    os.replace(final_dir, old / "d")
                    try:
                        os.replace(tmp, final_dir)
                    except BaseException:
                        os.replace(old / "d", final_dir)  # the earlier output goes back
                        raise
                    _TEMPORARIES.pop(tmp, None)
            finally:
                _discard(old)
        else:
            _into_place(tmp, final_dir)
    except OSError as err:  # a full disk, say: named as it would have been in the output
        _discard(tmp)
        name = str(err.filename or "")
        if err.errno not in REFUSED_ERRNOS or (name and not name.startswith(str(tmp))):
            raise
        raise CaptureError(f"{final_dir}{name[len(str(tmp)):]}: cannot write: {err.strerror or err}; "
                           "nothing was written") from None
    except CaptureError as err:  # a file of the output named by its temporary path: named as in the output
        _discard(tmp)
        if str(tmp) not in str(err):
            raise
        raise CaptureError(str(err).replace(str(tmp), str(final_dir))) from None
    except BaseException:
        _discard(tmp)
        raise
