"""A command's cache folder (`cache_dir`: G-buffers, per-pixel IBL tables) and XLA's
compilations kept beside it (`enable_compilation_cache`)."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import CaptureError
from ..fitting import runner
from ..render.views import default_cache_dir

__all__ = ["cache_dir", "enable_compilation_cache"]


def cache_dir(args):
    """The G-buffer (and XLA) cache folder of a command, or None; a path that is not a folder
    is refused."""
    if getattr(args, "no_cache", False):
        return None
    folder = Path(args.cache) if getattr(args, "cache", None) else default_cache_dir()
    if folder.exists() and not folder.is_dir():
        where = "--cache" if getattr(args, "cache", None) else "cache folder ($PBRFIT_CACHE, $XDG_CACHE_HOME/pbrfit or ~/.cache/pbrfit)"
        raise CaptureError(f"{where} {folder}: exists and is not a folder")
    return folder


def enable_compilation_cache(args) -> None:
    """Keep XLA compilations on disk beside the G-buffer cache, so a second run of a command
    loads its programs instead of compiling them (off with --no-cache or
    PBRFIT_NO_COMPILE_CACHE=1); the solver's among them, as it reports its steps after each solve,
    not by a host callback, which JAX would not keep."""

    if getattr(args, "no_cache", False) or os.environ.get("PBRFIT_NO_COMPILE_CACHE"):
        return

    try:
        folder = cache_dir(args)
    except CaptureError:  # not a folder: the commands that use the cache say so; the rest run uncached
        return
    try:
        runner.enable_compilation_cache(os.path.join(folder, "xla"))
    except Exception:  # an older or newer JAX without these options: run uncached
        pass
