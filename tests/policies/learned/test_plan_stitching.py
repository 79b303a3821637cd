"""Plan stitching: a re-plan continues the executed plan (no action step, no jerk spike)."""

from __future__ import annotations

import numpy as np
import pytest

from policies.riskflow.policy import RiskFlowAdversary
from riskflow_env.dynamics import rollout


def _adversary(models, stitch_steps: int, k: int = 0) -> RiskFlowAdversary:
    policy = RiskFlowAdversary(k=k, planning_interval=0.3, seed=2, **models)
    policy.stitch_steps = stitch_steps
    return policy


@pytest.mark.parametrize("k", [0, 2])
def test_replan_blends_into_the_executed_plan(tiny_meanflow, tiny_normalizer, closed_loop, k):
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    policy = _adversary(models, stitch_steps=5, k=k)
    env, emitted = closed_loop(policy, 3)  # cycle 0 planned at step 0, 3 steps executed
    previous = policy.plan_actions.copy()
    view = env.view()
    policy.act(view)  # step 3: cycle 1
    rows = np.flatnonzero(policy.plan_mask & view.active)
    assert rows.size > 0 and policy.cycles == 2

    fresh = _adversary(models, stitch_steps=0, k=k)  # the same cycle-1 plans, unblended
    fresh.reset(view)
    fresh.cycles, fresh._episode = 1, policy._episode
    fresh.plan(view)
    keep = np.array([5, 4, 3, 2, 1])[:, None] / 6.0
    expected = fresh.plan_actions[rows].copy()
    expected[:, :5] = keep * previous[rows, 3:8] + (1 - keep) * expected[:, :5]
    np.testing.assert_allclose(policy.plan_actions[rows], expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(policy.plan_actions[rows, 5:], fresh.plan_actions[rows, 5:])
    # The stored plans are what the actions do from the current state (same path).
    np.testing.assert_array_equal(
        policy.plans[rows], rollout(view.current[rows], policy.plan_actions[rows], policy.dynamics)
    )
    # The step into the new plan moves the action a sixth of the unblended switch.
    switch = np.abs(fresh.plan_actions[rows, 0] - previous[rows, 3])
    np.testing.assert_allclose(
        np.abs(policy.plan_actions[rows, 0] - previous[rows, 3]), switch / 6, atol=1e-12
    )
    unguided = rows[~policy.controllable[rows]]
    np.testing.assert_array_equal(policy.base_plans[unguided], policy.plans[unguided])
