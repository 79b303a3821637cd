"""The closed-loop harness under the default contact handling: a collision freezes both
vehicles, and the record's states, its event rows, its metrics and its video agree."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np

from policies.harness import ClosedLoop
from policies.planners import ConstantVelocityPlanner
from riskflow_env.agents import ReplayPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.geometry import separation
from tests.riskflow_env.hand_made_scenes import make_scenario

# agent_1 at 10 m/s runs into agent_2, standing 20 m ahead; the ego stands off to the side.
VEHICLES = [(0.0, -4.0, 0.0, 0.0), (15.0, 4.0, 10.0, 0.0), (35.0, 4.0, 0.0, 0.0)]
CONTACT_STEP = 16
STEPS = 30


def test_closed_loop_collision_freezes_the_pair_and_the_metrics_count_it_once(tmp_path):
    scenario = make_scenario(VEHICLES)
    config = EnvConfig(max_agents=3, episode_steps=STEPS)  # default termination rules
    video = tmp_path / "episode.gif"
    with ClosedLoop(ConstantVelocityPlanner(), ReplayPolicy(), config=config, video=video) as loop:
        record = loop.run(scenario)

    states = record.states  # (3, STEPS + 1, 4), index k after step k
    depth = -separation(states[1, :, :2], states[1, :, 3], 4.5, 2.0,
                        states[2, :, :2], states[2, :, 3], 4.5, 2.0)  # fmt: skip
    assert np.flatnonzero(depth > 0)[0] == CONTACT_STEP
    assert np.all(np.diff(depth[CONTACT_STEP:]) <= 0.0)
    assert not record.active[1:, CONTACT_STEP:].any() and record.active[1:, :CONTACT_STEP].all()
    np.testing.assert_array_equal(states[1:, CONTACT_STEP + 1 :, 2], 0.0)  # standing

    starts = [e for e in record.events if e["event"] == "collision_start"]
    ends = [e for e in record.events if e["event"] == "collision_end"]
    assert len(starts) == len(ends) == record.metrics["collisions"] == 1
    assert ends[0]["agents"] == starts[0]["agents"] == ["agent_1", "agent_2"]
    assert ends[0]["start_step"] == starts[0]["step"] == CONTACT_STEP
    assert ends[0]["cause"] == "done" and ends[0]["step"] == record.metrics["steps"] == STEPS
    assert record.metrics["time_to_first_collision"] == starts[0]["time"]
    assert not record.metrics["ego_collided"]
    assert len(iio.imread(video, index=None)) == STEPS + 1  # one frame after reset and each step
