"""The `pbrfit` command: argument parsing, progress and exit codes.

Each subcommand is a thin layer over the Python API, in a module of its own (`fit`, `render`,
`synth`, `demo`, `check_grads`, each with a ``run(args)``), imported only once its arguments are
parsed: the parser (`pbrfit.cli.parser`) loads no JAX, so ``--help`` and a usage error answer at
once. Bad input ends the command with one line on stderr, ``pbrfit: error: <what and where>``,
and exit status 2; nothing is half written.
"""

from __future__ import annotations

import functools
import importlib
import os
import signal
import sys
import warnings
from typing import Optional, Sequence

from .parser import EXIT_USAGE, build_parser
from ..errors import CaptureError, first_line
from ..io.atomic import REFUSED_ERRNOS

__all__ = ["main", "build_parser"]


def _run(module: str, args) -> int:
    """The command of `module` (``pbrfit.cli.<module>.run``) on its parsed arguments, with XLA's
    compilations kept on disk (`pbrfit.cli.cache.enable_compilation_cache`); its exit status."""
    # imported here, after parsing, not at the head: the commands load JAX and the fit's stack,
    # which the parser must not (--help and a usage error do not wait for them)
    from . import cache

    command = importlib.import_module(f"{__package__}.{module}")
    cache.enable_compilation_cache(args)
    return command.run(args)


#: Each command and the `pbrfit.cli` module that runs it (`_run`).
_COMMANDS = {name: functools.partial(_run, module) for name, module in (
    ("check-grads", "check_grads"), ("demo", "demo"), ("render", "render"), ("synth", "synth"), ("fit", "fit"))}
#: What to make smaller when a command runs out of memory.
_LESS = {"fit": "use a smaller --resolution (or fewer or smaller images)",
         "render": "use smaller or fewer images, a smaller material or a smaller --supersample",
         "synth": "use a smaller --size, --views, --supersample or --texture-size",
         "demo": "free some memory (the demo needs about 2 GB)"}


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread: unwinds like KeyboardInterrupt (outputs under a
    temporary name are removed on the way out)."""


def _stdout_closed() -> bool:
    """Whether stdout's reader has gone; if so, stdout is pointed at the null device, so that what
    is left in its buffer goes nowhere at exit instead of into a second error."""
    try:
        sys.stdout.flush()
        return False
    except BrokenPipeError:
        pass
    except (OSError, ValueError):
        return False
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    except (OSError, ValueError):  # stdout is no file descriptor
        pass
    return True


def _printable(text: str) -> str:
    """``text`` with each control character escaped as Python writes it (a newline or a terminal
    escape in a file name becomes ``\\n``, ``\\x1b``): a message stays one line, and shows the name."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line, like the errors: ``pbrfit: warning: <message>`` (`_printable`)."""
    print(f"pbrfit: warning: {_printable(str(message).rstrip()) if str(message) else category.__name__}",
          file=sys.stderr if file is None else file)


def _raise_terminated(signum, frame):
    raise _Terminated()


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the `pbrfit` console script; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:  # --help (0) or a usage error (2, one line already printed)
        return int(stop.code or 0)
    if args.command is None:
        print(f"pbrfit: error: expected a command, one of {', '.join(_COMMANDS)} (see pbrfit --help)", file=sys.stderr)
        return EXIT_USAGE
    # a `kill` (SIGTERM) unwinds like Ctrl-C, so that half-written outputs are removed
    try:
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
        installed = True
    except ValueError:  # not the main thread: signals stay as they are
        previous, installed = None, False
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            status = _COMMANDS[args.command](args)
            sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's last flush
            return status
    except BrokenPipeError:
        if not _stdout_closed():  # another pipe (a child's) broke: a bug, with its traceback
            raise
        return 141  # 128 + SIGPIPE, as a shell reports a command whose reader left (`| head -1`)
    except CaptureError as err:
        print(f"pbrfit: error: {_printable(str(err))}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        # the system refused a file (a name too long, a full disk, no permission, a read-only
        # place): one line naming it; anything else is a bug and keeps its traceback

        if err.errno not in REFUSED_ERRNOS:
            raise
        where = f"{err.filename}: " if err.filename else ""
        print(f"pbrfit: error: {_printable(f'{where}{err.strerror or err}')}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as err:
        # out of memory: numpy's MemoryError (its message names the size) or XLA's RESOURCE_EXHAUSTED;
        # anything else is a bug, and keeps its traceback
        if not (isinstance(err, MemoryError) or "RESOURCE_EXHAUSTED" in str(err)):
            raise

        hint = _LESS.get(args.command, "use smaller inputs")
        print(f"pbrfit: error: out of memory: {first_line(str(err))}; {hint}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("pbrfit: interrupted", file=sys.stderr)
        return 130
    except _Terminated:
        print("pbrfit: terminated", file=sys.stderr)
        return 143
    finally:
        if installed:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
