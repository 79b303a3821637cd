"""EventLogWrapper: onset/ending events, contact kinds, ego involvement, crash safety."""

from __future__ import annotations

import gc
import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest
import shapely
from pettingzoo.test import parallel_api_test

from riskflow_env.wrappers import EventLogWrapper, read_event_log
from riskflow_env.wrappers.event_log import contact_kind, contact_point
from tests.riskflow_env.hand_made_scenes import make_env


def run(env, path=None) -> EventLogWrapper:
    wrapped = EventLogWrapper(env, path)
    wrapped.reset(seed=0)
    while wrapped.agents:
        wrapped.step({agent: np.zeros(2) for agent in wrapped.agents})
    return wrapped


def of(events, kind):
    return [event for event in events if event["event"] == kind]


def test_rear_end_recorded_once_at_onset_and_end(tmp_path):
    # the ego (10 m/s) drives through a stopped car 12 m ahead: boxes overlap from
    # step 8 (gap 4 m < 4.5 m) until step 17 (gap 5 m)
    wrapped = run(make_env([(0.0, 0.0, 10.0, 0.0), (12.0, 0.0, 0.0, 0.0)]), tmp_path / "log.jsonl")
    events = wrapped.events
    assert [e["event"] for e in events] == ["collision_start", "collision_end", "episode_summary"]
    start, end, summary = events
    assert start["step"] == 8 and start["time"] == pytest.approx(0.8)
    assert start["agents"] == ["ego", "agent_1"] and start["ego_involved"] is True
    assert start["contact"] == ["front", "rear"]
    assert start["relative_speed"] == pytest.approx(10.0)
    assert start["positions"][1] == [12.0, 0.0]
    assert end["step"] == 17 and end["start_step"] == 8 and end["cause"] == "separated"
    assert end["duration"] == pytest.approx(0.9)
    assert summary["collisions"] == summary["ego_collisions"] == 1
    assert summary["ego_collided"] is True and summary["end_reason"] == "done"
    assert summary["time_to_first_collision"] == pytest.approx(0.8)
    assert summary["steps"] == 30
    assert read_event_log(tmp_path / "log.jsonl") == json.loads(json.dumps(events))
    wrapped.close()


def test_collision_between_others_does_not_involve_ego():
    vehicles = [(0.0, 8.0, 5.0, 0.0), (20.0, -4.0, 10.0, 0.0), (32.0, -4.0, 0.0, 0.0)]
    events = run(make_env(vehicles)).events
    (start,) = of(events, "collision_start")
    assert start["agents"] == ["agent_1", "agent_2"] and start["ego_involved"] is False
    (summary,) = of(events, "episode_summary")
    assert summary["collisions"] == 1 and summary["ego_collisions"] == 0
    assert summary["ego_collided"] is False and summary["time_to_first_ego_collision"] is None


def test_side_impact_contact_kinds():
    # agent_1 drives north into the flank of agent_2, which stands across its path
    # (slots are ordered by distance to the ego: agent_1 is the nearer one)
    vehicles = [(-30.0, -10.0, 0.0, 0.0), (40.0, -9.0, 10.0, np.pi / 2), (40.0, 0.0, 0.0, 0.0)]
    (start,) = of(run(make_env(vehicles, steps=10)).events, "collision_start")
    assert start["agents"] == ["agent_1", "agent_2"]
    assert start["contact"] == ["front", "side"]


@pytest.mark.parametrize(
    ("point", "kind"),
    [((2.0, 0.5), "front"), ((-2.2, -0.8), "rear"), ((0.5, 1.0), "side"), ((2.25, 1.0), "side")],
)
def test_contact_kind_in_vehicle_frame(point, kind):
    yaw = 0.7
    rotation = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    centre = np.array([3.0, -1.0])
    world = centre + rotation @ np.asarray(point)
    assert contact_kind(world, centre, yaw, 4.5, 2.0) == kind


def test_contact_point_is_overlap_centroid():
    point = contact_point(
        np.array([[0.0, 0.0], [4.0, 0.0]]), np.zeros(2), np.full(2, 4.5), np.full(2, 2.0)
    )
    np.testing.assert_allclose(point, [2.0, 0.0], atol=1e-9)  # overlap x in [1.75, 2.25]


def test_offroad_onset_and_end_with_depth():
    road = [shapely.box(-50.0, -6.0, 30.0, 6.0), shapely.box(40.0, -6.0, 250.0, 6.0)]
    events = run(make_env([(0.0, 0.0, 20.0, 0.0)], steps=30, road=road)).events
    (start,) = of(events, "offroad_start")
    (end,) = of(events, "offroad_end")
    assert start["agent"] == "ego" and start["ego_involved"] is True
    assert 0.0 < start["offroad_fraction"] <= 1.0 and start["sdf_depth"] > 0.0
    assert end["cause"] == "separated" and end["start_step"] == start["step"]
    assert end["max_sdf_depth"] >= start["sdf_depth"] and end["max_offroad_fraction"] == 1.0
    assert end["duration"] == pytest.approx((end["step"] - start["step"]) * 0.1)
    (summary,) = of(events, "episode_summary")
    assert summary["offroad_events"] == summary["ego_offroad_events"] == 1


def test_open_events_close_at_episode_end_and_reset():
    env = EventLogWrapper(make_env([(0.0, 0.0, 0.0, 0.0), (3.0, 0.5, 0.0, 0.0)], steps=5))
    env.reset(seed=0)
    env.step({agent: np.zeros(2) for agent in env.agents})
    env.reset(seed=0)  # abandons episode 0 with the overlap still open
    while env.agents:
        env.step({agent: np.zeros(2) for agent in env.agents})
    rows = [
        (e["episode"], e["event"], e["step"], e.get("cause", e.get("end_reason")))
        for e in env.events
    ]
    assert rows == [
        (0, "collision_start", 0, None),
        (0, "collision_end", 1, "reset"),
        (0, "episode_summary", 1, "reset"),
        (1, "collision_start", 0, None),
        (1, "collision_end", 5, "done"),
        (1, "episode_summary", 5, "done"),
    ]
    assert of(env.events, "collision_end")[1]["duration"] == pytest.approx(0.6)  # steps 0..5


@pytest.mark.reliability
def test_exception_in_with_block_writes_summary(tmp_path):
    path = tmp_path / "crash.jsonl"
    with (
        pytest.raises(RuntimeError),
        EventLogWrapper(make_env([(0.0, 0.0, 0.0, 0.0), (3.0, 0.0, 0.0, 0.0)]), path) as env,
    ):
        env.reset(seed=0)
        raise RuntimeError("planner crashed")
    kinds = [(e["event"], e.get("cause", e.get("end_reason"))) for e in read_event_log(path)]
    assert kinds == [
        ("collision_start", None),
        ("collision_end", "exception"),
        ("episode_summary", "exception"),
    ]


@pytest.mark.reliability
def test_unclosed_wrapper_finishes_its_log_when_collected(tmp_path):
    path = tmp_path / "dropped.jsonl"
    env = EventLogWrapper(make_env([(0.0, 0.0, 0.0, 0.0), (3.0, 0.0, 0.0, 0.0)]), path)
    env.reset(seed=0)
    del env
    gc.collect()  # weakref.finalize: the same hook runs at interpreter exit
    assert [e.get("cause", e.get("end_reason")) for e in read_event_log(path)] == [
        None,
        "exit",
        "exit",
    ]


def test_parallel_api():
    vehicles = [(0.0, 0.0, 10.0, 0.0), (12.0, 0.0, 0.0, 0.0), (20.0, 4.0, 5.0, 0.0)]
    parallel_api_test(EventLogWrapper(make_env(vehicles)), num_cycles=20)


CHILD = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[2])
from hand_made_scenes import make_env
from riskflow_env.wrappers import EventLogWrapper

# three pairs on separate lanes collide at different steps; a step waits for "go"
vehicles = [(0.0, 0.0, 10.0, 0.0), (6.0, 0.0, 0.0, 0.0), (0.0, 6.0, 10.0, 0.0),
            (14.0, 6.0, 0.0, 0.0), (0.0, -6.0, 10.0, 0.0), (22.0, -6.0, 0.0, 0.0)]
env = EventLogWrapper(make_env(vehicles, steps=60), sys.argv[1])
env.reset(seed=0)
while env.agents:
    env.step({agent: np.zeros(2) for agent in env.agents})
    print(len(env.events), flush=True)
    sys.stdin.readline()
"""


@pytest.mark.reliability
def test_killed_run_leaves_every_detected_event_on_disk(tmp_path):
    path = tmp_path / "killed.jsonl"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), os.path.dirname(os.path.dirname(__file__))],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        detected = 0
        while detected < 4:  # run until four events were detected, then kill -9
            line = child.stdout.readline()
            assert line, "the child exited before detecting four events"
            detected = int(line)
            if detected < 4:
                child.stdin.write("go\n")
                child.stdin.flush()
        child.send_signal(signal.SIGKILL)
        assert child.wait(timeout=30) == -signal.SIGKILL
    finally:
        child.kill()
        child.stdout.close()
        child.stdin.close()
    events = read_event_log(path)
    assert len(events) == detected
    assert [e["event"] for e in events].count("collision_start") >= 2
    assert "episode_summary" not in [e["event"] for e in events]
