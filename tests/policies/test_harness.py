"""Closed-loop runner: records, metrics, event log, replayable scenarios, summaries."""

from __future__ import annotations

import numpy as np
import pytest

from policies.harness import METRICS, ClosedLoop, summarize
from policies.planners import ConstantVelocityPlanner, IDMPlanner
from policies.statistics import mean_interval, wilson_interval
from riskflow_env.agents import IDMPolicy, ReplayPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.env import RiskFlowParallelEnv
from riskflow_env.maps import Lane, from_lanes
from riskflow_env.metrics import rollout_metrics
from riskflow_env.scenarios import Scenario, load_scenario, save_scenario, shipped_bank
from riskflow_env.wrappers import read_event_log

CONFIG = EnvConfig(episode_steps=30)


@pytest.fixture(scope="module")
def scene():
    return shipped_bank("eval")[1]  # merge


@pytest.fixture(scope="module")
def record(scene, tmp_path_factory):
    log = tmp_path_factory.mktemp("harness") / "events.jsonl"
    with ClosedLoop(IDMPlanner(), IDMPolicy(), config=CONFIG, event_log=log) as loop:
        result = loop.run(scene)
    assert read_event_log(log) == list(result.events)
    return result


def test_record_shapes_and_metrics(record, scene):
    steps = record.metrics["steps"]
    assert set(record.metrics) == set(METRICS)
    assert record.metrics["scenario"] == scene.name
    assert record.states.shape == (CONFIG.max_agents, steps + 1, 4)
    assert record.active.shape == record.offroad_centroid.shape == (CONFIG.max_agents, steps + 1)
    assert record.present.sum() == min(scene.num_agents, CONFIG.max_agents)
    assert np.array_equal(record.states[:, 0], np.asarray(record.scenario.states)[
        record.scenario_rows.clip(0), scene.current_index
    ] * record.present[:, None])  # fmt: skip
    assert record.events[-1]["event"] == "episode_summary"
    assert record.metrics["planning_cycles"] == steps  # IDM is asked every step


def test_rollout_record_agrees_with_the_metrics_module(record):
    row = rollout_metrics(record.rollout_record())
    assert row["ego_collision"] == float(record.metrics["ego_collided"])
    assert row["collision"] == float(record.metrics["collisions"] > 0)
    assert row["agent_steps"] > 0


def test_replaying_the_executed_scenario_reproduces_the_episode(record, tmp_path):
    path = save_scenario(record.to_scenario(), tmp_path / "executed.npz")
    replayed = load_scenario(path)
    assert replayed.ego_index == 0 and replayed.num_agents == record.present.sum()
    assert replayed.future_steps >= record.metrics["steps"]
    ego = ReplayPolicy(controlled=("ego",), mode="open_loop")

    class EgoReplay:  # the ego replays its own executed states too
        def reset(self, view):
            ego.reset(view)

        def __call__(self, observation, view):
            return ego.act(view)["ego"]

    with ClosedLoop(EgoReplay(), ReplayPolicy(mode="open_loop"), config=CONFIG) as loop:
        again = loop.run(replayed)
    present = record.present
    np.testing.assert_allclose(again.states[present], record.states[present], atol=1e-6)
    assert again.metrics["collisions"] == record.metrics["collisions"]


def test_seeded_draws_repeat(scene):
    with ClosedLoop(IDMPlanner(), IDMPolicy(), config=EnvConfig(episode_steps=10)) as loop:
        first, second = loop.run(seed=7), loop.run(seed=7)
    assert first.metrics["scenario"] == second.metrics["scenario"]
    np.testing.assert_array_equal(first.states, second.states)


def test_collision_metrics():
    road = from_lanes([Lane(np.array([[-100.0, 0.0], [300.0, 0.0]]), 3.5, "road")])
    states = np.zeros((2, 131, 4))
    states[0, :, 0], states[0, :, 2] = 10.0 * 0.1 * (np.arange(131) - 30), 10.0  # ego, 10 m/s
    states[1, :, 0] = 20.5  # standing 20.5 m ahead
    crash = Scenario(road, states, np.ones((2, 131), bool), np.full(2, 4.0), np.full(2, 2.0))
    with ClosedLoop(ConstantVelocityPlanner(), IDMPolicy(), scenarios=crash) as loop:
        record = loop.run(crash)
    metrics = record.metrics
    assert metrics["ego_collided"] and metrics["collisions"] == 1
    assert metrics["time_to_first_ego_collision"] == pytest.approx(1.7)  # 16.5 m gap at 10 m/s
    assert metrics["steps"] == 17  # the ego terminates on collision, the episode ends
    assert metrics["min_distance_to_ego"] <= 0.0
    assert metrics["orr_centroid"] == metrics["orr_footprint"] == 0.0
    assert not metrics["ego_offroad"]
    row = rollout_metrics(record.rollout_record())  # the metrics module agrees
    assert row["ego_collision"] == 1.0 and row["first_collision_step"] == 2 + 17  # 2 logged
    assert row["first_ego_collision_step"] == 2 + 17  # steps first


def test_intervals():
    low, high = wilson_interval(0, 10)
    assert low == 0.0 and high == pytest.approx(0.2775, abs=1e-4)  # Wilson, z = 1.96
    low, high = wilson_interval(5, 10)
    assert low == pytest.approx(0.2366, abs=1e-4) and high == pytest.approx(0.7634, abs=1e-4)
    assert np.isnan(wilson_interval(0, 0)).all() and np.isnan(mean_interval([1.0])).all()
    values = np.random.default_rng(0).normal(3.0, 1.0, 200)
    low, high = mean_interval(values)
    assert low < values.mean() < high and high - low == pytest.approx(0.28, abs=0.05)


def test_events_per_km_with_the_exact_poisson_interval():
    from policies.statistics import per_km

    none = per_km(0, 1000.0)  # no event in 1 km: [0, 3.69] (the "rule of three", exact)
    assert (none["value"], none["low"], none["n"]) == (0.0, 0.0, 0)
    assert none["high"] == pytest.approx(3.689, abs=1e-3)
    four = per_km(4, 2000.0)  # Garwood's interval of 4 events: [1.090, 10.242], over 2 km
    assert four["value"] == 2.0
    assert (four["low"], four["high"]) == pytest.approx((0.545, 5.121), abs=1e-3)
    assert per_km(3, 0.0) == {"value": None, "low": None, "high": None, "n": 3}


def test_summarize(record):
    summary = summarize([record, record])
    assert summary["ego_collision_rate"]["n"] == 2
    assert summary["ego_collision_rate"]["value"] == float(record.metrics["ego_collided"])
    if not record.metrics["ego_collided"]:
        assert summary["time_to_first_ego_collision"] == {
            "value": None, "low": None, "high": None, "n": 0
        }  # fmt: skip


def test_a_refused_event_log_leaves_nothing_open(scene, tmp_path, monkeypatch):
    log = tmp_path / "events.jsonl"
    log.write_text("{}\n")
    closed = []
    monkeypatch.setattr(RiskFlowParallelEnv, "close", lambda self: closed.append(self))
    with pytest.raises(FileExistsError):
        ClosedLoop(IDMPlanner(), IDMPolicy(), config=CONFIG, scenarios=scene, event_log=log)
    assert len(closed) == 1
