"""A fit ended by SIGTERM or SIGINT at any moment — importing, writing the G-buffer cache,
compiling, between solves, writing its output — exits within 2 s with 143 or 130, and leaves no
output folder and no temporary (in the output's folder or in the cache).

Each case runs ``python -m pbrfit.cli.main fit`` in a subprocess whose stdout and stderr are a
pseudo-terminal (so the fit shows its live progress line, one of the markers) and sends the
signal when a marker of the moment shows: the signal handler is set (``/proc/<pid>/status``), a
file appears in a fresh cache folder, JAX opens its compilation cache, the progress line shows a
step, the output's temporary folder appears. Linux only (``/proc``, ``pty``).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pbrfit.cli.main import main

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc and uses a pty")

#: How soon after the signal the command must have ended.
DEADLINE_S = 2.0
#: How long a marker may take to show (a cold start on a loaded machine).
MARKER_WAIT_S = 120.0
#: A cold compile of the fit's programs takes seconds: this long after JAX opens its compilation
#: cache, the fit is compiling.
INTO_COMPILE_S = 1.0
#: How often the markers are polled.
POLL_S = 0.002
#: Runs to stop the fit while it writes its output (some tens of milliseconds), before giving up.
FREEZE_TRIES = 3


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    cap = tmp_path_factory.mktemp("signals") / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "48", "--views", "3", "--quiet"]) == 0
    return cap


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory):
    """A cache folder the cases that run long share, so the later ones compile less."""
    return tmp_path_factory.mktemp("signals-cache")


class Fit:
    """``pbrfit fit`` in a subprocess on a pseudo-terminal, its output kept."""

    def __init__(self, capture: Path, out: Path, cache: Path):
        self.out, self.cache = out, cache
        master, slave = os.openpty()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "pbrfit.cli.main", "fit", str(capture), "--out", str(out), "--cache", str(cache)],
            cwd=out.parent, stdin=subprocess.DEVNULL, stdout=slave, stderr=slave)
        os.close(slave)
        self.text = ""
        self._reader = threading.Thread(target=self._read, args=(master,), daemon=True)
        self._reader.start()

    def _read(self, master: int) -> None:
        try:
            while data := os.read(master, 65536):
                self.text += data.decode(errors="replace")
        except OSError:  # the child closed the terminal
            pass
        finally:
            os.close(master)

    def handles_sigterm(self) -> bool:
        """Whether the command has set its SIGTERM handler (SigCgt: the signals it catches)."""
        try:
            status = Path(f"/proc/{self.proc.pid}/status").read_text()
        except OSError:
            return False
        caught = next(line for line in status.splitlines() if line.startswith("SigCgt:"))
        return bool(int(caught.split()[1], 16) >> (signal.SIGTERM - 1) & 1)

    def wait_for(self, marker, what: str) -> None:
        deadline = time.monotonic() + MARKER_WAIT_S
        while not marker():
            assert self.proc.poll() is None, f"the fit ended (status {self.proc.returncode}) before {what}:\n{self.text}"
            assert time.monotonic() < deadline, f"no {what} after {MARKER_WAIT_S} s:\n{self.text}"
            time.sleep(POLL_S)

    def end(self, signum: int, frozen: bool = False) -> float:
        """Send ``signum``; the seconds until the process ended. ``frozen``: the process was
        stopped (SIGSTOP) at the marker, and continues once the signal is pending."""
        start = time.monotonic()
        os.kill(self.proc.pid, signum)
        if frozen:
            os.kill(self.proc.pid, signal.SIGCONT)
        try:
            self.proc.wait(timeout=10 * DEADLINE_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        took = time.monotonic() - start
        self._reader.join(timeout=5)
        return took


def _leftovers(out: Path, cache: Path) -> list[str]:
    """Whatever an ended fit left that it should not: its output folder, the output's temporaries
    beside it, temporaries in the cache, a compilation-cache entry without its access time (JAX
    writes that after the entry)."""
    left = [p.name for p in out.parent.iterdir() if p.name == out.name or p.name.startswith(f".{out.name}.")]
    if cache.is_dir():
        left += [str(p) for p in cache.rglob("*") if ".tmp" in p.name]
        left += [str(p) for p in cache.glob("xla/*-cache")
                 if not p.with_name(p.name[: -len("-cache")] + "-atime").exists()]
    return left


def _files(folder: Path) -> bool:
    return folder.is_dir() and any(folder.iterdir())


def _output_temporary(out: Path):
    return lambda: any(p.name.startswith(f".{out.name}.") for p in os.scandir(out.parent))


#: Each moment: the cache it uses ("fresh" or "shared"), its marker, and whether the process is
#: stopped at the marker (the output's writing lasts some tens of milliseconds: stopped, the fit
#: cannot finish it before the signal is pending).
MOMENTS = {
    "importing": ("fresh", lambda fit: fit.handles_sigterm, False),
    "writing the G-buffer cache": ("fresh", lambda fit: lambda: _files(fit.cache), False),
    "compiling": ("fresh", lambda fit: lambda: (fit.cache / "xla").is_dir(), False),
    "between solves": ("shared", lambda fit: lambda: " step " in fit.text, False),
    "writing the output": ("shared", lambda fit: _output_temporary(fit.out), True),
}


@pytest.mark.parametrize("moment", list(MOMENTS))
def test_sigterm_ends_a_fit_at_once_leaving_nothing(capture, shared_cache, tmp_path, moment):
    which, marker, freeze = MOMENTS[moment]
    cache = tmp_path / "cache" if which == "fresh" else shared_cache
    for _ in range(FREEZE_TRIES):
        fit = Fit(capture, tmp_path / "out", cache)
        fit.wait_for(fit.handles_sigterm, "SIGTERM handler")
        fit.wait_for(marker(fit), moment)
        if not freeze:
            break
        os.kill(fit.proc.pid, signal.SIGSTOP)
        if not (tmp_path / "out").exists():  # stopped before the output was renamed into place
            break
        fit.end(signal.SIGCONT)  # this machine was too slow to stop it in time: let it finish, and again
        shutil.rmtree(tmp_path / "out")
    else:
        pytest.fail(f"the fit never stopped while {moment} ({FREEZE_TRIES} tries)")
    if moment == "compiling":
        time.sleep(INTO_COMPILE_S)
    took = fit.end(signal.SIGTERM, frozen=freeze)
    assert fit.proc.returncode == 143, fit.text
    assert took < DEADLINE_S, f"{took:.2f} s after SIGTERM"
    assert fit.text.rstrip().endswith("pbrfit: terminated"), fit.text
    assert _leftovers(tmp_path / "out", cache) == []


def test_sigint_while_compiling_exits_130(capture, tmp_path):
    fit = Fit(capture, tmp_path / "out", tmp_path / "cache")
    fit.wait_for(fit.handles_sigterm, "SIGTERM handler")
    fit.wait_for(lambda: (fit.cache / "xla").is_dir(), "compiling")
    time.sleep(INTO_COMPILE_S)
    took = fit.end(signal.SIGINT)
    assert fit.proc.returncode == 130, fit.text
    assert took < DEADLINE_S, f"{took:.2f} s after SIGINT"
    assert fit.text.rstrip().endswith("pbrfit: interrupted"), fit.text
    assert _leftovers(tmp_path / "out", tmp_path / "cache") == []
