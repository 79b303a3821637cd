"""A planner under test that raises: one line naming the episode and step, and the reports
of the episodes that finished before it."""

from __future__ import annotations

import json
import pickle
import textwrap

import numpy as np
import pytest

from policies.stress import riskflow_stress
from policies.stress.cli import main
from policies.stress.runner import (
    GuardedPlanner,
    PlannerError,
    PlannerFailed,
    StressInterrupted,
)

STEPS = 30
LATE = textwrap.dedent(
    """
    import numpy as np

    class Late:
        '''Drives straight on, then raises on its 41st call: in the second episode.'''

        def __init__(self):
            self.calls = 0

        def __call__(self, observation, view):
            self.calls += 1
            if self.calls > 40:
                raise RuntimeError("boom inside the planner")
            return np.zeros(2)
    """
)


def test_the_command_names_the_planner_episode_and_step(tmp_path, capsys):
    planner = tmp_path / "late.py"
    planner.write_text(LATE)
    out = tmp_path / "out"
    argv = ["--planner", f"{planner}:Late", "--scenes", "2", "--steps", str(STEPS)]
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--gifs", "0", "--no-progress", "--out", str(out)])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith(
        "riskflow-stress: error: the planner raised RuntimeError: boom inside the planner "
        "(scene 1 (merge-eval-s0-00001), seed 0, step 10); 1 of 2 episodes finished before it"
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] == {"episodes": 1, "planned": 2, "cause": "the planner raised"}
    assert summary["episodes"] == 1
    assert "1 episode (the planner raised: 1 of 2)" in (out / "report.md").read_text()


def test_the_python_function_raises_with_the_finished_episodes(tmp_path):
    namespace: dict = {}
    exec(LATE, namespace)
    with pytest.raises(PlannerFailed, match="step 10") as error:
        riskflow_stress(namespace["Late"](), scenes=2, steps=STEPS, progress=False)
    assert len(error.value.episodes) == 1 and error.value.planned == 2
    assert isinstance(error.value, PlannerError) and isinstance(error.value, ValueError)


class _Wide:
    """Returns an action of three numbers on its 41st call."""

    def __init__(self):
        self.calls = 0

    def __call__(self, observation, view):
        self.calls += 1
        return np.zeros(3 if self.calls > 40 else 2)


def test_an_action_of_the_wrong_shape_is_the_planners_error_too():
    with pytest.raises(PlannerFailed, match=r"ValueError: planner must return .* step 10"):
        riskflow_stress(_Wide(), scenes=2, steps=STEPS, progress=False)


def test_a_ctrl_c_inside_the_planner_stays_an_interrupt():
    """A numba planner turns Ctrl-C into a SystemError around it: not the planner's error."""

    def interrupted(observation, view):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("returned a result with an exception set") from None

    guarded = GuardedPlanner(interrupted)
    with pytest.raises(SystemError):
        guarded(np.zeros(4), None)


def test_the_errors_pickle_with_their_episodes():
    error = pickle.loads(pickle.dumps(PlannerFailed("boom", [], 3)))
    assert (str(error), error.episodes, error.planned) == ("boom", [], 3)
    stop = pickle.loads(pickle.dumps(StressInterrupted([], 4)))
    assert (str(stop), stop.planned) == ("0 of 4 episodes finished", 4)
