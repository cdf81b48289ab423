"""The stages after the solve run behind one protocol (`pbrfit.fitting.stages.pipeline`)."""

import dataclasses

import numpy as np

from pbrfit import FitOptions
from pbrfit.fitting.stages.pipeline import STAGES, TURNED_OFF, StageState, run_stages, stage_steps


@dataclasses.dataclass
class _Stage:
    name: str
    off: bool = False
    why: str = None
    found: dict = None

    def turned_off(self, options):
        return self.off

    def skipped(self, state):
        return self.why

    def run(self, state):
        state.xs = state.xs + 1.0  # what a stage changes, the next one sees
        return dict(self.found, seen_x=float(state.xs[0, 0]))


def _state():
    return StageState(FitOptions(), None, None, None, np.zeros((2, 5), np.float32), (None, None), (1, 2),
                      np.ones(2, bool), np.ones(5, np.float32), 10, 4, {})


def test_run_stages_runs_skips_and_summarises_each_stage_alike():
    stages = [_Stage("a", found=dict(steps=3)), _Stage("b", off=True), _Stage("c", why="not here"),
              _Stage("d", found=dict(passes=[dict(steps=2), dict(steps=5)])),
              _Stage("e", found=dict(metallic=dict(steps=4), roughness=dict(steps=1), note="x"))]
    state = _state()
    clock = {}
    entries, summary = run_stages(stages, state, clock)
    assert entries["b"] == dict(skipped=TURNED_OFF) and entries["c"] == dict(skipped="not here")
    assert entries["a"]["seen_x"] == 1.0 and entries["d"]["seen_x"] == 2.0 and entries["e"]["seen_x"] == 3.0
    assert float(state.xs[0, 0]) == 3.0
    assert [s["name"] for s in summary] == list("abcde")
    assert [s["ran"] for s in summary] == [True, False, False, True, True]
    assert [s["skipped"] for s in summary] == [None, TURNED_OFF, "not here", None, None]
    assert [s["steps"] for s in summary] == [3, 0, 0, 7, 5]
    assert all(s["seconds"] >= 0 for s in summary)
    assert set(clock) == {"a", "d", "e"}  # each stage that ran has its own time


def test_stage_steps_reads_each_findings_shape():
    assert stage_steps(dict(steps=6, texels=3)) == 6
    assert stage_steps(dict(passes=[dict(steps=1), dict(kind="outliers", steps=2)], other=dict(steps=99))) == 3
    assert stage_steps(dict(metallic=dict(steps=4), roughness=dict(uniform=True))) == 4


def test_the_fit_stages_are_turned_off_by_their_options():
    repair, uniform, hold = STAGES
    assert [s.name for s in STAGES] == ["repair", "uniform_check", "unconstrained"]
    assert not any(s.turned_off(FitOptions()) for s in STAGES)
    assert repair.turned_off(FitOptions(repair=False)) and not uniform.turned_off(FitOptions(repair=False))
    assert uniform.turned_off(FitOptions(uniform_check=False))
    assert hold.turned_off(FitOptions(unconstrained_sigma=float("inf")))
    state = _state()  # a uniform material (1 x 1 maps would be (1, 1)): here 1 x 2, all channels fitted
    assert repair.skipped(dataclasses.replace(state, final=(1, 1))) == "a uniform material"
    assert uniform.skipped(dataclasses.replace(state, options=FitOptions(loss="huber"))).startswith("needs the l2 loss")
    assert hold.skipped(dataclasses.replace(state, options=FitOptions(smooth=0.1))) == \
        "the smoothness prior already ties the texels together"
