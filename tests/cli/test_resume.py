"""`pbrfit fit --resume`: a fit killed (SIGKILL) mid-solve goes on from its checkpoint to the maps
of a fit never interrupted, running fewer steps; a checkpoint of other options is refused; with no
checkpoint the fit starts afresh."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from pbrfit.cli.main import main
from pbrfit.fitting.checkpoint import checkpoint_folder

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kills a process")

#: How long the killed fit may take to journal its first steps (a cold start on a loaded machine).
WAIT_S = 120.0
#: Runs to catch the fit mid-solve (it may finish between two looks), before giving up.
TRIES = 3
#: The fit: small, and long enough to be caught in its solve.
FLAGS = ["--resolution", "16", "--max-steps", "40", "--quiet"]
MAPS = ("base_color.exr", "metallic.exr", "roughness.exr", "uncertainty.exr", "coverage.exr", "convergence.png")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    cap = tmp_path_factory.mktemp("resume") / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "32", "--views", "3", "--texture-size", "8",
                 "--quiet"]) == 0
    return cap


def _journaled_steps(index) -> int:
    try:
        return sum(e["info"]["steps"] for e in json.loads(index.read_text())["entries"])
    except (OSError, ValueError, KeyError):  # not there yet
        return 0


def _killed_mid_solve(capture, out) -> None:
    """Start ``pbrfit fit`` and SIGKILL it as soon as its checkpoint holds solver steps."""
    index = checkpoint_folder(out) / "checkpoint.json"
    for _ in range(TRIES):
        proc = subprocess.Popen([sys.executable, "-m", "pbrfit.cli.main", "fit", str(capture), "--out", str(out)]
                                + FLAGS, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + WAIT_S
        while _journaled_steps(index) == 0 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        if proc.returncode == -signal.SIGKILL and not out.exists():
            return
        assert proc.returncode in (0, -signal.SIGKILL), proc.stderr.read().decode()
        for path in (out, checkpoint_folder(out)):  # it finished first: again
            subprocess.run(["rm", "-rf", str(path)], check=True)
    pytest.fail(f"the fit was never caught mid-solve ({TRIES} tries)")


def test_a_killed_fit_resumes_to_the_maps_of_one_never_interrupted(capture, tmp_path, capsys):
    whole = tmp_path / "whole"  # (--resume with no checkpoint there: a fit from the start)
    assert main(["fit", str(capture), "--out", str(whole), "--resume"] + FLAGS) == 0
    assert not checkpoint_folder(whole).exists()  # removed once the output is written
    report = json.loads((whole / "report.json").read_text())
    assert report["resumed"] is None

    out = tmp_path / "out"
    _killed_mid_solve(capture, out)
    folder = checkpoint_folder(out)
    assert folder.parent == out.parent and _journaled_steps(folder / "checkpoint.json") > 0
    # a checkpoint of other options is refused, in one line naming it and the difference, and kept
    capsys.readouterr()
    assert main(["fit", str(capture), "--out", str(out), "--resume", "--max-steps", "30", "--resolution", "16"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(folder) in err[0] and "--max-steps 40 there, 30 now" in err[0], err
    assert not out.exists() and (folder / "checkpoint.json").is_file()

    assert main(["fit", str(capture), "--out", str(out), "--resume"] + FLAGS) == 0
    for name in MAPS:
        assert (out / name).read_bytes() == (whole / name).read_bytes(), name
    resumed = json.loads((out / "report.json").read_text())
    assert resumed["steps"] == report["steps"]
    went_on = resumed["resumed"]
    assert went_on["solver_runs_replayed"] > 0 and 0 < went_on["steps_replayed"] < report["steps"], went_on
    assert not folder.exists() and not any("checkpoint" in p.name for p in out.rglob("*"))

