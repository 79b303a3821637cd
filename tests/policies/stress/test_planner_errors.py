"""A planner under test that raises: one line naming the episode and step, and the reports
of the episodes that finished before it."""

from __future__ import annotations

import json
import textwrap

import pytest

from policies.stress import riskflow_stress
from policies.stress.cli import main
from policies.stress.runner import PlannerError, PlannerFailed

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
    assert summary["interrupted"] == {"episodes": 1, "planned": 2} and summary["episodes"] == 1


def test_the_python_function_raises_with_the_finished_episodes(tmp_path):
    namespace: dict = {}
    exec(LATE, namespace)
    with pytest.raises(PlannerFailed, match="step 10") as error:
        riskflow_stress(namespace["Late"](), scenes=2, steps=STEPS, progress=False)
    assert len(error.value.episodes) == 1 and error.value.planned == 2
    assert isinstance(error.value, PlannerError) and isinstance(error.value, ValueError)
