"""A fit's checkpoint (`pbrfit.fitting.checkpoint`): solver runs journaled and replayed by the
runner, a structured run killed between its parts going on from the state kept, to the bit, and a
checkpoint of another fit refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pbrfit.errors import CaptureError
from pbrfit.fitting import runner
from pbrfit.fitting.checkpoint import Checkpoint, checkpoint_folder, folder_digests
from pbrfit.fitting.initialisation import grid_initialise
from pbrfit.fitting.runner import Compiler, Runner
from pbrfit.fitting.solvers.structured import StructuredLM
from test_sharding import _problem, _start

FINGERPRINT = {"pbrfit": "0", "options": {"--max-steps": 30}, "files": {"capture a.png": "1"}}


class _Killed(Exception):
    """The process ending at once, as after SIGKILL: what the checkpoint holds is what is left."""


class _KilledAtSave(Checkpoint):
    """A checkpoint whose process ends right after its ``at``-th save of a run's state."""

    at = 2

    def save_partial(self, *args):
        super().save_partial(*args)
        self.at -= 1
        if self.at == 0:
            raise _Killed


def _runs(checkpoint):
    """A runner's two runs, as a fit's continuation starts: the Jacobian at the start (a run of
    0 steps), then 30 steps; (x, info, linearisation) of each and the losses reported."""
    problem, _ = _problem(smooth=1e-3)
    x0 = np.asarray(grid_initialise(_start(problem), problem))
    reported = []
    run = Runner(StructuredLM(rtol=1e-9, atol=0.0), lambda k, e, budget: reported.append((k, float(e))),
                 Compiler(dict(compile=0.0, solve=0.0), background=False), checkpoint)
    num_free = int(np.sum(np.asarray(problem.free)))
    outs = []
    for steps in (0, 30):
        x, info = run(x0, problem, steps, num_free)
        outs.append((x, info, tuple(np.asarray(a) for a in run.linearization)))
    return outs, reported


def test_a_run_killed_between_its_parts_goes_on_from_the_state_kept(tmp_path, monkeypatch):
    monkeypatch.setattr(runner, "MIN_PART_STEPS", 1)  # a part per step
    whole, whole_reported = _runs(None)
    folder = tmp_path / "out.pbrfit-checkpoint"
    with pytest.raises(_Killed):
        _runs(_KilledAtSave(folder, FINGERPRINT, seconds=0.0))
    saved = json.loads((folder / "checkpoint.json").read_text())
    assert len(saved["entries"]) == 1 and saved["partial"]["number"] == 1 and saved["partial"]["steps"] == 2

    checkpoint = Checkpoint(folder, FINGERPRINT, resume=True, seconds=0.0)
    resumed, reported = _runs(checkpoint)
    assert whole[1][1]["steps"] > 2
    for (x, info, lin), (x_r, info_r, lin_r) in zip(whole, resumed):
        np.testing.assert_array_equal(x, x_r)
        assert info == info_r
        for a, b in zip(lin, lin_r):  # the replayed run's linearisation: step 0 at its x
            np.testing.assert_array_equal(a, b)
    assert reported == whole_reported  # the convergence plot's losses, the replayed ones too
    assert checkpoint.resumed() == dict(solver_runs_replayed=1, steps_replayed=2, at=dict(solver_run=1, step=2))


def test_a_checkpoint_of_another_fit_is_refused_in_one_line(tmp_path):
    folder = checkpoint_folder(tmp_path / "out")
    assert folder.name == "out.pbrfit-checkpoint" and folder.parent == tmp_path
    Checkpoint(folder, FINGERPRINT).record(0, "id", np.zeros(3, np.float32), dict(steps=0), [])
    changed = dict(FINGERPRINT, files={"capture a.png": "2"})
    with pytest.raises(CaptureError, match=r"out\.pbrfit-checkpoint: a checkpoint of another fit \(capture a\.png "
                                           r"has changed\); run without --resume") as err:
        Checkpoint(folder, changed, resume=True)
    assert "\n" not in str(err.value)
    other = dict(FINGERPRINT, options={"--max-steps": 40})
    with pytest.raises(CaptureError, match="--max-steps 30 there, 40 now"):
        Checkpoint(folder, other, resume=True)
    Checkpoint(folder, other)  # without --resume it is replaced
    assert not folder.exists()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(CaptureError, match="is not a pbrfit checkpoint"):  # a folder of the user's, kept
        Checkpoint(tmp_path / "mine", FINGERPRINT)


def test_folder_digests_name_each_file_and_leave_out_hidden_and_skipped_ones(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "0.png").write_bytes(b"a")
    (tmp_path / ".hidden").write_bytes(b"b")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "report.json").write_bytes(b"c")
    digests = folder_digests(tmp_path, skip=(tmp_path / "out",))
    assert list(digests) == ["images/0.png"]
    (tmp_path / "images" / "0.png").write_bytes(b"A")
    assert folder_digests(tmp_path, skip=(tmp_path / "out",)) != digests


def test_the_runs_of_several_runners_are_journaled_each_under_its_own_number(tmp_path):
    """A fit may make several runners (the footprint's and the light model's choices fit again):
    their runs are numbered on in the checkpoint, each journaled, and all replayed on resume."""
    folder = tmp_path / "cp"
    first = Checkpoint(folder, FINGERPRINT)
    outs = _runs(first)[0] + _runs(first)[0]
    assert [e["file"] for e in json.loads((folder / "checkpoint.json").read_text())["entries"]] == [
        f"call-{n:04d}.npy" for n in range(4)]
    again = Checkpoint(folder, FINGERPRINT, resume=True)
    replayed = _runs(again)[0] + _runs(again)[0]
    assert again.replayed == 4
    for (x, _, _), (y, _, _) in zip(outs, replayed):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
