"""A resumed event log keeps counting episodes after a killed run (issue 19 item 5)."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from riskflow_env.wrappers import EventLogWrapper, read_event_log
from tests.riskflow_env.hand_made_scenes import make_env

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

VEHICLES = [(0.0, 0.0, 0.0, 0.0), (3.0, 0.0, 0.0, 0.0)]


def _run(path, episodes, **kwargs):
    with EventLogWrapper(make_env(VEHICLES, steps=3), path, **kwargs) as env:
        for _ in range(episodes):
            env.reset(seed=0)
            while env.agents:
                env.step({agent: (0.0, 0.0) for agent in env.agents})


def test_append_continues_the_episode_numbers(tmp_path):
    path = tmp_path / "events.jsonl"
    _run(path, 2)
    _run(path, 2, append=True)
    summaries = [e["episode"] for e in read_event_log(path) if e["event"] == "episode_summary"]
    assert summaries == [0, 1, 2, 3]


def test_append_after_a_kill_mid_episode(tmp_path):
    path = tmp_path / "events.jsonl"
    _run(path, 1)
    torn = '{"event": "collision_start", "episode": 1, "step": 0, "time": 0.0}\n{"event": "co'
    with open(path, "a", encoding="utf-8") as file:
        file.write(torn)  # killed inside episode 1, mid-write
    with pytest.warns(UserWarning, match="torn"):
        _run(path, 1, append=True)
    episodes = [e["episode"] for e in read_event_log(path)]
    assert episodes == sorted(episodes) and episodes[-1] == 2  # 1 was the killed one


KILLED = """
import os, signal, sys
import numpy as np
sys.path.insert(0, sys.argv[2])
from hand_made_scenes import make_env
from riskflow_env.wrappers import EventLogWrapper

vehicles = [tuple(map(float, v.split(","))) for v in sys.argv[3].split(";")]
env = EventLogWrapper(make_env(vehicles, steps=20), sys.argv[1])
for episode in range(3):
    env.reset(seed=0)
    while env.agents:
        env.step({agent: np.zeros(2) for agent in env.agents})
        if episode == 1 and env.unwrapped.scene.step == 10:
            os.kill(os.getpid(), signal.SIGKILL)  # kill -9 mid-episode, nothing closed
"""

# two pairs that collide at different steps of every 20-step episode
KILL_VEHICLES = [(0.0, 0.0, 10.0, 0.0), (6.0, 0.0, 0.0, 0.0), (0.0, 6.0, 10.0, 0.0),
                 (14.0, 6.0, 0.0, 0.0)]  # fmt: skip


def _events_by_episode(path):
    episodes = {}
    for event in read_event_log(path):
        episodes.setdefault(event["episode"], []).append(
            {k: v for k, v in event.items() if k != "episode"}
        )
    return episodes


def test_kill_9_mid_episode_then_resume_loses_nothing(tmp_path):
    """Issue 19 deliverable 6: kill -9 of a logging run, then a resume with append=True:
    every event detected before the kill is on disk, the resumed episodes continue the
    numbering and log what an uninterrupted run logs."""
    reference = tmp_path / "reference.jsonl"
    with EventLogWrapper(make_env(KILL_VEHICLES, steps=20), reference) as env:
        for _ in range(3):
            env.reset(seed=0)
            while env.agents:
                env.step({agent: (0.0, 0.0) for agent in env.agents})
    path = tmp_path / "killed.jsonl"
    vehicles = ";".join(",".join(map(str, v)) for v in KILL_VEHICLES)
    child = subprocess.run(
        [sys.executable, "-c", KILLED, str(path), str(Path(__file__).parents[1]), vehicles],
        capture_output=True,
        text=True,
        timeout=600,  # a hang guard only: the machine may be loaded
    )
    assert child.returncode == -signal.SIGKILL, child.stderr[-2000:]
    expected = _events_by_episode(reference)
    killed = _events_by_episode(path)
    assert killed[0] == expected[0]  # the finished episode, summary included
    before_kill = [e for e in expected[1] if e["step"] <= 10 and e["event"] != "episode_summary"]
    assert killed[1] == before_kill and before_kill  # every event detected before the kill
    with EventLogWrapper(make_env(KILL_VEHICLES, steps=20), path, append=True) as env:
        for _ in range(2):  # the killed episode again, then the last one
            env.reset(seed=0)
            while env.agents:
                env.step({agent: (0.0, 0.0) for agent in env.agents})
    resumed = _events_by_episode(path)
    assert sorted(resumed) == [0, 1, 2, 3]
    assert resumed[2] == expected[1] and resumed[3] == expected[2]
