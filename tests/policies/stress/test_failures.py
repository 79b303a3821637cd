"""Failure analysis: the collision types on hand-built collisions, an avoidable collision
whose witness keeps clear when rolled out, and an unavoidable one (the ego boxed in at
rest) that is not called avoidable."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import shapely

from policies.harness import ClosedLoop
from policies.planners import ConstantVelocityPlanner
from policies.stress import (
    CLEARANCE,
    HUMAN_BOUNDS,
    EscapeSearch,
    analyse,
    collision_type,
    kinematic_bounds,
)
from policies.stress.failures import kinematic_p99
from policies.stress.summary import Analysed, stress_summary
from riskflow_env.agents.replay import ReplayPolicy
from riskflow_env.config import DynamicsConfig, EnvConfig
from riskflow_env.dynamics import step as dynamics_step
from riskflow_env.geometry import footprint_points, separation
from riskflow_env.scenarios import shipped_bank
from tests.riskflow_env.hand_made_scenes import make_scenario

SIZE = np.array([[4.5, 2.0], [4.5, 2.0]])
SMALL = EscapeSearch(samples=64, refine=4, steps=30)  # a small search budget
DT = 0.1


def track(final, steps: int = 20, lateral_speed: float = 0.0) -> np.ndarray:
    """(steps + 1, 4) constant-velocity states ending at ``final`` (x, y, v, yaw), drifting
    sideways (world y) at ``lateral_speed`` [m/s]."""
    x, y, v, yaw = final
    back = np.arange(-steps, 1) * DT
    return np.stack(
        [
            x + v * np.cos(yaw) * back,
            y + v * np.sin(yaw) * back + lateral_speed * back,
            np.full(back.shape, v),
            np.full(back.shape, yaw),
        ],
        axis=-1,
    )


@pytest.mark.parametrize(
    ("other", "lateral", "expected"),
    [
        ((-4.4, 0.0, 15.0, 0.0), 0.0, "struck_from_behind"),
        ((4.4, 0.0, 5.0, 0.0), 0.0, "striking_from_behind"),
        ((4.3, 0.8, 8.0, 0.0), -2.0, "cut_in"),  # 3.8 m to the left 1.5 s before
        ((0.5, 1.9, 10.0, 0.0), -1.0, "side_swipe"),  # 3.4 m to the left 1.5 s before
        ((4.4, 0.2, 10.0, np.pi), 0.0, "head_on"),
        ((3.0, 2.5, 10.0, -np.pi / 2), 0.0, "crossing"),
    ],
)
def test_collision_types(other, lateral, expected):
    ego = track((0.0, 0.0, 10.0, 0.0))
    assert collision_type(ego, track(other, lateral_speed=lateral), SIZE, DT) == expected


def closed_loop(vehicles, road, steps: int = 40):
    """The ego drives at constant velocity, the others replay their constant-velocity
    tracks open loop; returns the episode record."""
    config = EnvConfig(max_agents=len(vehicles), episode_steps=steps)
    scenario = make_scenario(vehicles, road=road, steps=steps + 30)
    with ClosedLoop(ConstantVelocityPlanner(), ReplayPolicy(mode="open_loop"), config) as loop:
        return loop.run(scenario)


def test_struck_from_behind_at_speed_is_avoidable_and_the_witness_keeps_clear():
    road = shapely.box(-60.0, -6.0, 120.0, 6.0)
    record = closed_loop([(0.0, 0.0, 8.0, 0.0), (-20.0, 0.0, 18.0, 0.0)], road)
    (failure,) = analyse(record)
    assert failure.type == "struck_from_behind" and not failure.standing_ego
    assert failure.attacker == "agent_1" and failure.reaction_time == 0.0 and not failure.wreck
    assert failure.avoidable and failure.escape.clearance >= CLEARANCE
    # the witness, rolled out step by step by the env's dynamics, keeps clear and on road
    dynamics = DynamicsConfig()
    state = record.states[0, 0]
    others = record.states[1]
    for index, action in enumerate(failure.escape.actions, start=1):
        state = dynamics_step(state, action, dynamics)
        np.testing.assert_allclose(state, failure.escape.states[index], atol=1e-6)
        other = others[min(index, others.shape[0] - 1)]
        if index < others.shape[0]:
            gap = separation(state[:2], state[3], 4.5, 2.0, other[:2], other[3], 4.5, 2.0)
            assert gap >= CLEARANCE - 1e-9
        points = footprint_points(state[:2], state[3:4], 4.5, 2.0)
        assert (record.scenario.map.sdf_at(points) <= 1e-9).all()


def test_ego_boxed_in_at_rest_is_not_called_avoidable():
    road = shapely.box(-60.0, -4.2, 120.0, 4.2)  # room for three cars abreast, no more
    vehicles = [
        (0.0, 0.0, 0.0, 0.0),  # the ego, standing
        (-25.0, 0.0, 15.0, 0.0),  # strikes it from behind
        (5.0, 0.0, 0.0, 0.0),  # a standing car 0.5 m ahead
        (0.0, 2.1, 0.0, 0.0),  # and one on either side
        (0.0, -2.1, 0.0, 0.0),
    ]
    record = closed_loop(vehicles, road)
    (failure,) = analyse(record, search=EscapeSearch(samples=64, refine=4, steps=30))
    assert failure.type == "struck_from_behind" and failure.standing_ego
    assert failure.searched and not failure.avoidable
    summary = stress_summary([Analysed(record, (failure,))])
    assert summary["ego_collision_rate"]["value"] == 1.0
    assert summary["avoidable_failure_rate"]["value"] == 0.0
    assert summary["standing_strike_share"]["value"] == 1.0
    assert summary["types"]["struck_from_behind"] == {"collisions": 1, "avoidable": 0}


def test_an_attack_without_reaction_time_is_not_avoidable():
    road = shapely.box(-60.0, -6.0, 120.0, 6.0)
    record = closed_loop([(0.0, 0.0, 8.0, 0.0), (-20.0, 0.0, 18.0, 0.0)], road)
    guided = np.zeros(record.in_scene.shape, dtype=bool)
    guided[1, 12:] = True  # the attack starts 1.2 s in, the impact comes before 2.2 s
    late = type(record)(**{**record.__dict__, "guided": guided})
    (failure,) = analyse(late)
    assert failure.attack_start == pytest.approx(1.2)
    assert failure.reaction_time == pytest.approx(2.2)
    assert failure.time < failure.reaction_time
    assert not failure.searched and not failure.avoidable


def test_the_ego_running_into_a_wreck_is_flagged_and_the_freeze_is_not_driving():
    """The vehicle ahead of the ego strikes a standing car at 2.0 s and the env freezes
    both; the ego strikes the wreck at 2.6 s. The wreck's stop is the env's contact rule,
    not its driving: its p99 is measured up to its first contact."""
    road = shapely.box(-60.0, -6.0, 120.0, 6.0)
    vehicles = [(0.0, 0.0, 12.0, 0.0), (8.0, 0.0, 14.0, 0.0), (40.5, 0.0, 0.0, 0.0)]
    record = closed_loop(vehicles, road)
    (failure,) = analyse(record, search=SMALL)
    assert failure.attacker == "agent_1" and failure.type == "striking_from_behind"
    assert failure.wreck and failure.attacker_speed == 0.0
    assert failure.plausible and failure.attacker_p99["accel"] < 0.1
    summary = stress_summary([Analysed(record, (failure,))])
    assert summary["wreck_share"]["value"] == 1.0
    # guided only after its contact: still measured over the last second before it
    guided = np.zeros(record.in_scene.shape, dtype=bool)
    guided[1, 25:] = True
    (late,) = analyse(type(record)(**{**record.__dict__, "guided": guided}), search=SMALL)
    contact = next(e["step"] for e in record.events if e["event"] == "collision_start")
    expected = kinematic_p99(record.states[1, contact - 10 : contact + 1], record.dt)
    assert late.attacker_p99 == expected and late.attack_start == pytest.approx(2.5)


def test_human_bounds_are_the_training_banks_p99():
    measured = kinematic_bounds(shipped_bank("train"))
    for name in ("accel", "jerk", "yaw_rate"):
        assert getattr(measured, name) == pytest.approx(getattr(HUMAN_BOUNDS, name), rel=1e-3)


def test_the_rl_evaluation_reports_the_avoidable_failure_rate():
    from policies.rl.evaluation import summarize_ego

    road = shapely.box(-60.0, -6.0, 120.0, 6.0)
    avoidable = closed_loop([(0.0, 0.0, 8.0, 0.0), (-20.0, 0.0, 18.0, 0.0)], road)
    clear = closed_loop([(0.0, 0.0, 8.0, 0.0), (20.0, 4.0, 8.0, 0.0)], road, steps=10)
    summary = summarize_ego([avoidable, clear])
    assert summary["avoidable_failure_rate"]["value"] == 0.5
    assert summary["ego_collision_rate"]["value"] == 0.5
    assert summary["slow_ego_share"]["value"] == 0.0  # the ego drives at 8 m/s throughout


def test_the_rl_table_shows_the_slow_ego_share_and_reads_older_summaries():
    from policies.rl.report import markdown_table

    entry = {"value": 0.5, "low": 0.1, "high": 0.9, "n": 4}
    new = {"ego_collision_rate": entry, "slow_ego_share": entry | {"value": 0.678}}
    old = {"ego_collision_rate": entry}  # a results.json written before the column existed
    table = markdown_table({("ppo", "K=5"): new, ("idm", "K=5"): old},
                           ("ego_collision_rate", "slow_ego_share"))  # fmt: skip
    header, _, ppo, idm = table.splitlines()
    assert "ego steps below 2 m/s" in header
    assert "0.678 [0.100, 0.900]" in ppo and idm.endswith("| – | 4 |")


def test_a_bound_held_exactly_is_within_it():
    """Finite differences read a vehicle braking at exactly the bound a hair over it."""
    exact = {"accel": 6.000000000000004, "jerk": 20.0, "yaw_rate": 0.3}
    assert HUMAN_BOUNDS.admit(exact)
    assert not HUMAN_BOUNDS.admit(exact | {"accel": 6.001})
    assert not HUMAN_BOUNDS.admit(exact | {"jerk": 28.0})


def test_coverage_counts_the_attacked_episodes_and_the_slow_ego_steps():
    road = shapely.box(-60.0, -6.0, 120.0, 6.0)
    # the ego stands for the whole episode; another car drives by in the next lane
    record = closed_loop([(0.0, 0.0, 0.0, 0.0), (-30.0, 3.5, 10.0, 0.0)], road, steps=20)
    assert record.guided is None  # replay traffic has no controllable set
    outcome = Analysed(record, ()).outcome()
    assert outcome["attacked_steps"] is None and outcome["slow_ego_steps"] == 20
    guided = np.zeros(record.states.shape[:2], dtype=bool)
    guided[1, 5:12] = True  # guided for 7 steps
    guided[1, -1] = True  # the last column repeats the one before: not a step of its own
    attacked = dataclasses.replace(record, guided=guided)
    assert Analysed(attacked, ()).outcome()["attacked_steps"] == 7
    summary = stress_summary([Analysed(attacked, ()), Analysed(record, ())])
    # the replay episode has no controllable set: it is left out of the attacked rate
    assert summary["attacked_rate"]["value"] == 1.0 and summary["attacked_rate"]["n"] == 1
    assert summary["slow_ego_share"]["value"] == 1.0 and summary["slow_ego_share"]["n"] == 2
    unguided = dataclasses.replace(record, guided=np.zeros_like(guided))
    summary = stress_summary([Analysed(attacked, ()), Analysed(unguided, ())])
    assert summary["attacked_rate"]["value"] == 0.5
    # results files written before the coverage fields existed still summarise
    old = dict(Analysed(record, ()).outcome())
    del old["attacked_steps"], old["slow_ego_steps"]
    summary = stress_summary([old])
    assert summary["attacked_rate"]["n"] == 0 and summary["slow_ego_share"]["n"] == 0
    # collisions per km: over the distance of every episode (here 2 km, no collision)
    per_km = stress_summary([{**old, "progress": 500.0}, {**old, "progress": 1500.0}])
    entry = per_km["ego_collisions_per_km"]
    assert entry["value"] == 0.0 and entry["high"] == pytest.approx(3.689 / 2, abs=1e-3)
