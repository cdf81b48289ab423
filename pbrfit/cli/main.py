"""The `pbrfit` command: argument parsing, progress and exit codes.

Each subcommand is a thin layer over the Python API, in a module of its own (`fit`, `render`,
`synth`, `demo`, `check_grads`, each with a ``run(args)``), imported only once its arguments are
parsed: the parser (`pbrfit.cli.parser`) loads no JAX, so ``--help`` and a usage error answer at
once. Bad input ends the command with one line on stderr, ``pbrfit: error: <what and where>``,
and exit status 2; nothing is half written.

On its own command line (the console script, ``python -m pbrfit.cli.main``) the command runs in a
worker thread while the main thread waits, free to take signals: SIGINT and SIGTERM end the
process within a moment, even while XLA computes or compiles, with exit status 130 or 143 and
every temporary output removed (`_end_on_signal`); a command that returns ends the process at
once, without the interpreter's teardown (`_end_now`).
"""

from __future__ import annotations

import functools
import importlib
import os
import signal
import sys
import threading
import warnings
from typing import Optional, Sequence

from .parser import EXIT_USAGE, build_parser
from ..errors import CaptureError, first_line
from ..io.atomic import REFUSED_ERRNOS, abandon_writes

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
    _point_at_null(sys.stdout.fileno)
    return True


def _point_at_null(descriptor) -> None:
    """Point the file descriptor ``descriptor()`` gives at the null device (nothing where it
    cannot: stdout is no file descriptor, or the system refuses)."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, descriptor())
        os.close(null)
    except (OSError, ValueError):
        pass


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


#: The signals that end a command, and the word its last line says.
_ENDING_SIGNALS = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}
#: A shell's exit status for a command a signal ended: this plus the signal's number (130, 143).
_SIGNAL_STATUS_BASE = 128
#: How long a signal waits for a rename into place, or for a compilation-cache entry being written,
#: to finish (each takes milliseconds; the process ends within 2 s of the signal).
_FINISH_WRITE_S = 0.5
#: How often the main thread wakes while it waits for the command's worker: a signal that reached
#: another thread (XLA's) runs its handler at the next wake.
_WAKE_S = 0.05


def _end_on_signal(signum, frame):
    """SIGINT or SIGTERM while the command runs in its worker thread: remove every temporary the
    atomic writers have made and not renamed into place (`pbrfit.io.atomic.abandon_writes`, which
    waits for a rename under way and keeps any later one from happening), say so in one line and
    end the process with status 128 + the signal's number (130, 143). ``os._exit``: the worker
    may be inside XLA, which can be neither interrupted nor joined."""
    for number in _ENDING_SIGNALS:  # a second signal meanwhile changes nothing
        signal.signal(number, signal.SIG_IGN)
    abandon_writes(_FINISH_WRITE_S)
    _silence_stdout()
    try:
        sys.stderr.flush()
    except (OSError, ValueError):  # a reader gone, a stream closed
        pass
    try:
        os.write(2, f"pbrfit: {_ENDING_SIGNALS[signum]}\n".encode())
    except OSError:
        pass
    os._exit(_SIGNAL_STATUS_BASE + signum)


#: On a terminal: show the cursor (a live progress line hides it until it stops) and clear the line.
_TERMINAL_RESET = "\x1b[?25h\r\x1b[2K"


def _silence_stdout() -> None:
    """Flush stdout (on a terminal, reset after a progress line: `_TERMINAL_RESET`), then point it
    at the null device, so that nothing the worker or a progress line's refresh thread writes
    meanwhile comes after the command's last line."""
    try:
        if sys.stdout.isatty():
            sys.stdout.write(_TERMINAL_RESET)
        sys.stdout.flush()
    except (OSError, ValueError):  # a reader gone, a stream closed
        pass
    _point_at_null(lambda: 1)


def _in_worker(command, args):
    """``command(args)`` in a daemon thread while this (the main) thread waits for it, so that the
    signal handlers run at once; its result, or its exception raised here."""
    outcome = {}

    def work():
        try:
            outcome["status"] = command(args)
        except BaseException as err:  # raised again in the main thread, where main() reports it
            outcome["error"] = err

    worker = threading.Thread(target=work, name="pbrfit-command", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(_WAKE_S)
    if "error" in outcome:
        raise outcome.pop("error")
    return outcome["status"]


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the `pbrfit` console script; returns the exit status.

    Without ``argv`` (the process's own command line) and in the main thread, the command runs in
    a worker thread and SIGINT or SIGTERM ends the process at once (`_end_on_signal`, exit status
    130 or 143); with ``argv`` (the command called from Python) it runs in the caller's thread and
    a signal unwinds it (Ctrl-C's KeyboardInterrupt, SIGTERM alike), main() returning 130 or 143.
    Either way no output is left half written."""
    detached = argv is None and threading.current_thread() is threading.main_thread()
    # a `kill` (SIGTERM) unwinds like Ctrl-C, so that half-written outputs are removed; installed
    # first, so that a signal while the arguments are read ends the command alike
    handlers = {signal.SIGINT: _end_on_signal, signal.SIGTERM: _end_on_signal} if detached else \
        {signal.SIGTERM: _raise_terminated}
    previous = {}
    try:
        for number, handler in handlers.items():
            previous[number] = signal.signal(number, handler)
    except ValueError:  # not the main thread: signals stay as they are
        pass
    try:
        status = _main(argv, detached)
        if detached:
            _end_now(status)
        return status
    finally:
        for number, handler in previous.items():
            signal.signal(number, signal.SIG_DFL if handler is None else handler)


def _end_now(status: int) -> None:
    """End the process with ``status`` once its command has returned: its outputs are in place and
    its last lines are flushed here, so the interpreter's teardown is skipped (JAX's backends and
    arrays, and a compile the fit started and no longer needs, which an exit waits for): 0.4 s
    of a cold peer fit's 10.5. A compilation-cache entry being written is waited for, as on a
    signal (`abandon_writes`)."""
    abandon_writes(_FINISH_WRITE_S)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a reader gone, a stream closed
            pass
    os._exit(status)


def _main(argv: Optional[Sequence[str]], detached: bool) -> int:
    """`main` once its signal handlers are set."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:  # --help (0) or a usage error (2, one line already printed)
        return int(stop.code or 0)
    if args.command is None:
        print(f"pbrfit: error: expected a command, one of {', '.join(_COMMANDS)} (see pbrfit --help)", file=sys.stderr)
        return EXIT_USAGE
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            command = _COMMANDS[args.command]
            status = _in_worker(command, args) if detached else command(args)
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
        print(f"pbrfit: {_ENDING_SIGNALS[signal.SIGINT]}", file=sys.stderr)
        return _SIGNAL_STATUS_BASE + signal.SIGINT
    except _Terminated:
        print(f"pbrfit: {_ENDING_SIGNALS[signal.SIGTERM]}", file=sys.stderr)
        return _SIGNAL_STATUS_BASE + signal.SIGTERM


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
