"""Contact handling: by default both vehicles of a collision freeze where they touched
(``EnvConfig.terminate_on_collision="all"``); the state, the event log and the frames agree."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env import render
from riskflow_env.config import EnvConfig
from riskflow_env.geometry import separation
from riskflow_env.wrappers import EventLogWrapper
from tests.riskflow_env.hand_made_scenes import make_scenario

# A standing ego off to the side; agent_1 at 10 m/s runs into agent_2, standing 20 m ahead:
# the boxes (4.5 m long) first overlap at step 16, 0.5 m deep.
VEHICLES = [(0.0, -4.0, 0.0, 0.0), (15.0, 4.0, 10.0, 0.0), (35.0, 4.0, 0.0, 0.0)]
CONTACT_STEP = 16
STEPS = 30
SCALE = 8.0  # [px/m] of the default view, centred on the ego at (0, -4)


def run(render_mode: str | None = None, **config):
    """Drive the scene at constant speed (zero actions) to the end of the episode; returns
    the env, the pair's overlap depth [m] per step and, with a render mode, the frames."""
    scenario = make_scenario(VEHICLES)
    env = riskflow_env.parallel_env(
        config=EnvConfig(max_agents=3, episode_steps=STEPS, **config),
        scenarios=scenario,
        render_mode=render_mode,
    )
    env = EventLogWrapper(env)
    env.reset(seed=0)
    base = env.unwrapped
    depths, states, frames, done_at = [], [], [], {}
    while env.agents:
        _, _, terminations, truncations, _ = env.step({a: np.zeros(2) for a in env.agents})
        for agent in terminations:
            if terminations[agent] or truncations[agent]:
                done_at[agent] = (base.scene.step, terminations[agent])
        current = base.scene.current
        depths.append(-float(separation(current[1, :2], current[1, 3], 4.5, 2.0,
                                        current[2, :2], current[2, 3], 4.5, 2.0)))  # fmt: skip
        states.append(current.copy())
        if render_mode:
            frames.append(base.render())
    env.close()
    return env, np.array(depths), np.array(states), frames, done_at


def test_both_vehicles_freeze_at_first_contact_and_the_overlap_does_not_grow():
    env, depths, states, _, done_at = run()
    contact = int(np.flatnonzero(depths > 0)[0]) + 1  # depths[k] is after step k + 1
    assert contact == CONTACT_STEP
    assert done_at["agent_1"] == done_at["agent_2"] == (CONTACT_STEP, True)  # terminated
    assert np.all(np.diff(depths[contact - 1 :]) <= 0.0)  # never deeper than at contact
    # Frozen where they touched: same position and heading from the contact step on, speed
    # 0 from the next step (the contact step keeps the impact speed the event log reports).
    frozen = states[contact - 1 :, 1:]
    pose = frozen[:, :, [0, 1, 3]]
    np.testing.assert_array_equal(pose, np.broadcast_to(pose[:1], pose.shape))
    np.testing.assert_array_equal(frozen[1:, :, 2], 0.0)
    assert states[contact - 1, 1, 2] == 10.0
    assert done_at["ego"] == (STEPS, False)  # the ego drives on to the time limit

    events = [e for e in env.events if e["event"].startswith("collision")]
    assert [e["event"] for e in events] == ["collision_start", "collision_end"]
    start, end = events
    assert start["agents"] == end["agents"] == ["agent_1", "agent_2"]
    assert start["step"] == end["start_step"] == CONTACT_STEP
    assert start["relative_speed"] == 10.0
    assert end["cause"] == "done" and end["step"] == STEPS  # in contact until the end
    assert end["duration"] == pytest.approx((STEPS + 1 - CONTACT_STEP) * 0.1)
    summary = env.events[-1]
    assert summary["collisions"] == 1 and not summary["ego_collided"]
    assert summary["time_to_first_collision"] == pytest.approx(CONTACT_STEP * 0.1)


def test_with_ego_only_termination_the_others_drive_through_each_other():
    env, depths, states, _, done_at = run(terminate_on_collision="ego")
    contact = int(np.flatnonzero(depths > 0)[0])
    assert depths[contact + 2] > depths[contact] + 1.0  # the boxes sink into each other
    assert "agent_1" not in done_at or done_at["agent_1"][0] == STEPS
    assert np.all(states[contact:, 1, 2] == 10.0)
    assert sum(e["event"] == "collision_start" for e in env.events) == 1


def test_a_frozen_pair_is_drawn_done_with_the_collision_outline_and_stands_still():
    _, _, _, frames, _ = run(render_mode="rgb_array")

    def pixel(x: float, y: float) -> tuple[int, int]:
        return round(180 - (y + 4.0) * SCALE), round(320 + x * SCALE)

    before, at_contact, last = frames[CONTACT_STEP - 2], frames[CONTACT_STEP - 1], frames[-1]
    rear_of_agent_1 = pixel(31.0 - 1.8, 4.0)  # inside the box, behind its heading mark
    assert tuple(before[pixel(30.0 - 1.8, 4.0)]) == render.OTHER
    for frame in (at_contact, last):
        assert tuple(frame[rear_of_agent_1]) == render.DONE
        assert tuple(frame[pixel(31.0 - 2.25, 4.0)]) == render.COLLISION  # outline, rear edge
        assert tuple(frame[pixel(35.0 + 2.25, 4.0)]) == render.COLLISION  # agent_2's front
    # Nothing of the pair moves on screen from the contact step to the last frame.
    (top, left), (bottom, right) = pixel(31.0 - 2.25, 5.0), pixel(35.0 + 2.25, 3.0)
    np.testing.assert_array_equal(
        at_contact[top : bottom + 1, left : right + 1], last[top : bottom + 1, left : right + 1]
    )
