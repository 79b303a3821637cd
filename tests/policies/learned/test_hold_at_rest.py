"""Holding at rest (``AdversaryConfig.hold_distance``): a vehicle at rest whose new plan
hardly moves it keeps its brake on; every other plan is left as it is."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from policies.baselines.nominal import NominalGenerator
from policies.learned.adversary_config import AdversaryConfig
from policies.learned.plan_stitching import REST_SPEED
from policies.riskflow.policy import RiskFlowAdversary
from riskflow_env.config import EnvConfig
from riskflow_env.dynamics import rollout
from riskflow_env.scenarios import shipped_bank

SCENE = 17  # an intersection of the shipped evaluation bank, 7 vehicles at rest


@pytest.fixture(scope="module")
def view():
    scenario = shipped_bank("eval")[SCENE]
    env = riskflow_env.parallel_env(scenarios=scenario, config=EnvConfig(episode_steps=30))
    env.reset(seed=0, options={"scenario": scenario})
    return env.view()


def _planned(models, view, hold: float, k: int = 0) -> RiskFlowAdversary:
    policy = RiskFlowAdversary(k=k, planning_interval=0.5, seed=3, hold_distance=hold, **models)
    policy.reset(view)
    policy.plan(view)
    return policy


@pytest.mark.parametrize("k", [0, 2])
def test_vehicles_at_rest_with_short_plans_are_held(tiny_meanflow, tiny_normalizer, view, k):
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    free = _planned(models, view, 0.0, k)
    at_rest = free.plan_mask & view.active & (view.current[:, 2] <= REST_SPEED)
    assert at_rest.sum() >= 2
    reach = np.linalg.norm(free.plans[..., :2] - view.current[:, None, :2], axis=-1).max(axis=1)
    distance = float(np.median(reach[at_rest]))  # holds some of them, not all
    held = at_rest & (reach < distance)
    assert 0 < held.sum() < at_rest.sum()

    policy = _planned(models, view, distance, k)
    actions = policy.plan_actions
    # held: no positive acceleration, no yaw rate, the rest of the plan's braking kept
    np.testing.assert_array_equal(actions[held, :, 0], np.minimum(free.plan_actions[held, :, 0], 0))
    assert (actions[held, :, 1] == 0).all()
    stays = np.linalg.norm(policy.plans[held, :, :2] - view.current[held, None, :2], axis=-1)
    assert stays.max() <= REST_SPEED * policy.horizon * view.dt
    np.testing.assert_array_equal(
        policy.plans[held], rollout(view.current[held], actions[held], policy.dynamics)
    )
    # everything else: the plans of the policy without it, bit for bit
    others = policy.plan_mask & ~held
    np.testing.assert_array_equal(actions[others], free.plan_actions[others])
    np.testing.assert_array_equal(policy.plans[others], free.plans[others])
    unguided = policy.plan_mask & ~policy.controllable
    np.testing.assert_array_equal(policy.base_plans[unguided], policy.plans[unguided])


def test_held_vehicles_stay_in_closed_loop(tiny_meanflow, tiny_normalizer, closed_loop):
    """With a distance no plan reaches, every vehicle at rest stays at rest: its speed
    never rises above where it started, across re-plans and their stitching."""
    scenario = shipped_bank("eval")[SCENE]
    config = EnvConfig(episode_steps=30)
    env = riskflow_env.parallel_env(scenarios=scenario, config=config)
    env.reset(seed=0, options={"scenario": scenario})
    start = env.view().current.copy()
    at_rest = start[:, 2] <= REST_SPEED
    at_rest[0] = False  # the ego
    policy = NominalGenerator(
        planning_interval=0.5, seed=0, generator=tiny_meanflow, normalizer=tiny_normalizer,
        hold_distance=1e6,
    )  # fmt: skip
    env, _ = closed_loop(policy, 30, scenario=scenario, config=config)  # 6 cycles
    end = env.view().current
    assert at_rest.sum() >= 5 and policy.cycles == 6
    assert (end[at_rest, 2] <= start[at_rest, 2] + 1e-9).all()
    moved = np.linalg.norm(end[at_rest, :2] - start[at_rest, :2], axis=1)
    assert (moved <= start[at_rest, 2] * 3.0 + 1e-9).all()  # at most its speed for 3 s
    np.testing.assert_array_equal(end[at_rest, 3], start[at_rest, 3])  # no turn in place


def test_hold_distance_is_checked():
    for bad in (-1.0, float("nan"), float("inf"), True, "1"):
        with pytest.raises(ValueError, match="hold_distance"):
            AdversaryConfig(hold_distance=bad)
    assert AdversaryConfig(hold_distance=2).hold_distance == 2.0
