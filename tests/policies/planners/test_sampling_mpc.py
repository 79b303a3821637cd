"""Lane keeping at constant speed, the sampling MPC, the oracle and the plans it reads."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from policies.harness import ClosedLoop
from policies.planners import (
    IDMPlanner,
    LaneKeepingPlanner,
    OraclePlanner,
    SamplingMPCPlanner,
    reset_planner,
)
from policies.planners.sampling_mpc import ConstantVelocityPrediction, candidate_actions
from policies.riskflow import RiskFlowAdversary
from policies.rl.features import ManeuverFeatures
from riskflow_env.agents import ConstantVelocityPolicy
from riskflow_env.scenarios.io import shipped_bank
from tests.policies.planners.test_planners import start, stopped_car_scene


class ConstantVelocityPlans(ConstantVelocityPolicy):
    """Constant-velocity traffic that also tells what it will do (the oracle's input)."""

    predicted_states = ConstantVelocityPrediction().predicted_states


def test_lane_keeping_steers_like_idm_but_never_brakes():
    env, observations = start(stopped_car_scene())
    lane, idm = LaneKeepingPlanner(), IDMPlanner()
    for planner in (lane, idm):
        reset_planner(planner, env.view())
    accel, yaw_rate = lane(observations["ego"], env.view())
    assert accel == 0.0 and yaw_rate == idm(observations["ego"], env.view())[1]
    with ClosedLoop(LaneKeepingPlanner(), ConstantVelocityPolicy()) as loop:
        assert loop.run(stopped_car_scene()).metrics["ego_collided"]  # into the stopped car


def test_candidate_actions_are_distinct_lane_change_shapes():
    candidates = candidate_actions(30)
    assert candidates.shape == (200, 30, 2)  # 8 accels x (8 turning yaw rates x 3 shapes + 1)
    assert len(np.unique(candidates, axis=0)) == len(candidates)
    assert np.all(candidates[..., 0] == candidates[:, :1, 0])  # one acceleration per sequence
    turns = np.abs(candidates[..., 1]).sum(axis=1) > 0
    heading_change = candidates[..., 1].sum(axis=1)
    # lane changes (5 and 15 steps each way) end on the heading they started with
    assert np.sum(turns & (np.abs(heading_change) < 1e-9)) == 8 * 8 * 2


@pytest.mark.parametrize("which", ["sampling_mpc", "oracle"])
def test_mpc_avoids_the_stopped_car_that_constant_velocity_hits(which):
    traffic = ConstantVelocityPlans()
    planner = SamplingMPCPlanner() if which == "sampling_mpc" else OraclePlanner(traffic)
    with ClosedLoop(planner, traffic) as loop:
        record = loop.run(stopped_car_scene())
    assert not record.metrics["ego_collided"]
    assert not record.metrics["ego_offroad"]
    assert record.metrics["steps"] == 100  # drove the whole episode


def test_constant_velocity_prediction_extrapolates(road_view):
    _, view = road_view()  # six cars at 12 m/s along +x
    ahead = ConstantVelocityPrediction().predicted_states(view, 10)
    assert ahead.shape == (view.num_agents, 10, 4)
    ahead, now = ahead[view.present], view.history[view.present, -1]
    np.testing.assert_allclose(ahead[..., 0], now[:, None, 0] + 1.2 * np.arange(1, 11))
    np.testing.assert_allclose(ahead[..., 1:], np.broadcast_to(now[:, None, 1:], (6, 10, 3)))


def test_oracle_needs_plans_to_read():
    with pytest.raises(TypeError, match="predicted_states"):
        OraclePlanner(ConstantVelocityPolicy())
    env, observations = start(stopped_car_scene())
    with pytest.raises(RuntimeError, match="watch"):
        OraclePlanner()(observations["ego"], env.view())
    with pytest.raises(ValueError, match="horizon"):
        SamplingMPCPlanner(horizon=0)
    with pytest.raises(ValueError, match="gamma"):
        OraclePlanner(gamma=0.0)


def test_predicted_states_follow_the_plan_buffer(tiny_meanflow, tiny_normalizer, closed_loop):
    policy = RiskFlowAdversary(
        k=0, planning_interval=0.5, seed=0, generator=tiny_meanflow, normalizer=tiny_normalizer
    )
    with pytest.raises(RuntimeError, match="act"):
        policy.predicted_states(None, 3)
    env, _ = closed_loop(policy, 3)  # planned at step 0, acted at steps 0, 1, 2
    view = env.view()
    policy.act(view)  # step 3: still the plan of step 0
    ahead = policy.predicted_states(view, 60)
    horizon = policy.plans.shape[1]
    np.testing.assert_array_equal(ahead[:, : horizon - 3], policy.plans[:, 3:])
    np.testing.assert_array_equal(
        ahead[:, horizon - 3 :], policy.plans[:, -1:].repeat(63 - horizon, 1)
    )
    with pytest.raises(ValueError, match="steps"):
        policy.predicted_states(view, 0)


def test_maneuver_features_see_the_stopped_car_ahead():
    from policies.rl.features import ACCELS, CAP, ManeuverFeatures

    env, _ = start(stopped_car_scene())  # 35.5 m gap at 15 m/s, a 3.5 m wide road
    features = ManeuverFeatures()
    values = features(env.view())
    candidates = features.planner.candidates
    count = len(candidates)
    assert values.shape == (features.size,) == (2 * count,)
    gap, edge = values[:count], values[count:]
    straight = np.abs(candidates[..., 1]).sum(axis=1) == 0
    by_accel = {a: gap[straight & (candidates[:, 0, 0] == a)][0] for a in ACCELS}
    assert by_accel[3.0] <= 0.0 < by_accel[-5.0]  # accelerating hits it, braking stops short
    assert np.all(edge[straight] < 0) and np.all(edge[~straight] > 0)  # one lane: turns leave it
    assert np.all(np.abs(values) <= CAP)


def test_outcomes_skip_only_pairs_beyond_exact_below():
    """Pairs certainly farther than ``exact_below`` are skipped: every gap up to it is the
    exact one, larger ones stay larger; costs and the RL features do not change."""
    env = riskflow_env.parallel_env(scenarios=shipped_bank("eval"))
    planner, traffic = SamplingMPCPlanner(), ConstantVelocityPolicy(controlled="all")
    skipped = 0
    for seed in range(3):
        env.reset(seed=seed)
        for _ in range(10):
            env.step(traffic.act(env.view()))
        view = env.view()
        _, exact, edge = planner.outcomes(view)
        _, gap, culled_edge = planner.outcomes(view, exact_below=5.0)
        assert np.isfinite(exact).all() and np.array_equal(edge, culled_edge)
        close = exact <= 5.0
        assert close.any() and np.allclose(gap[close], exact[close], rtol=0, atol=1e-9)
        assert np.all(gap[~close] > 5.0)
        skipped += np.sum(gap > exact)  # the nearest vehicle, beyond 5 m, was skipped
        # the cost reads min(gap, clearance_cap = 5 m) and the RL features clip at 10 m
        assert np.allclose(np.minimum(gap, 5.0), np.minimum(exact, 5.0), rtol=0, atol=1e-9)
        features = ManeuverFeatures()
        assert np.allclose(features(view), np.clip(np.concatenate(
            [features.planner.outcomes(view)[1].min(-1), features.planner.outcomes(view)[2].max(-1)]
        ), -10, 10), rtol=0, atol=1e-6)  # fmt: skip
    assert skipped  # the bound does skip far vehicles on these scenes
