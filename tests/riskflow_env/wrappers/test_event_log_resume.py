"""A resumed event log keeps counting episodes after a killed run (issue 19 item 5)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from riskflow_env.wrappers import EventLogWrapper, read_event_log

_spec = importlib.util.spec_from_file_location(
    "_event_log_tests", Path(__file__).with_name("test_event_log.py")
)
_tests = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_tests)

VEHICLES = [(0.0, 0.0, 0.0, 0.0), (3.0, 0.0, 0.0, 0.0)]


def _run(path, episodes, **kwargs):
    with EventLogWrapper(_tests.make_env(VEHICLES, steps=3), path, **kwargs) as env:
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
