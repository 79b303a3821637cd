"""Plan stitching: a re-plan continues the executed plan (no action step, no jerk spike)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from policies.baselines.diffusion.policy import DiffusionAdversary
from policies.learned.adversary_config import AdversaryConfig
from policies.learned.plan_stitching import (
    CORRECTION_STITCH_STEPS,
    DEFAULT_FIRST_STITCH_STEPS,
    DEFAULT_STITCH_STEPS,
    blend_share,
    continuation,
)
from policies.pipeline import stages
from policies.pipeline.plan_set import PlanSet
from policies.riskflow.policy import RiskFlowAdversary
from riskflow_env.dynamics import rollout


def _adversary(models, stitch_steps: int, k: int = 0) -> RiskFlowAdversary:
    """Blending after planning, as the diffusion baselines do: the MeanFlow adversary's
    cycle without its ``stitch`` stage."""
    policy = RiskFlowAdversary(
        k=k, planning_interval=0.3, seed=2, stitch_steps=stitch_steps, **models
    )
    policy.stages = tuple(stage for stage in policy.stages if stage is not stages.stitch)
    return policy


def _same_cycle(fresh, policy) -> None:
    """``fresh`` draws the noise of ``policy``'s next cycle."""
    fresh.state = fresh.state.replace(cycles=1, episode=policy.state.episode)


def test_stitch_steps_is_a_checked_shared_option(tiny_meanflow, tiny_normalizer, tiny_denoiser):
    assert AdversaryConfig().stitch_steps is None  # the blend that goes with the method
    assert AdversaryConfig(stitch_steps=np.int64(10)).stitch_steps == 10
    for bad in (-1, 2.5, True, "5"):
        with pytest.raises(ValueError, match="stitch_steps must be None or an int >= 0"):
            AdversaryConfig(stitch_steps=bad)
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    # the MeanFlow adversaries blend first over 15 steps, the others after over 5
    assert RiskFlowAdversary(k=0, **models).stitch_steps == DEFAULT_FIRST_STITCH_STEPS == 15
    assert stages.stitch in RiskFlowAdversary(k=0, **models).stages
    assert DEFAULT_STITCH_STEPS == 5
    assert RiskFlowAdversary(k=0, stitch_steps=7, **models).stitch_steps == 7
    diffusion = DiffusionAdversary(k=0, denoiser=tiny_denoiser, normalizer=tiny_normalizer)
    assert stages.stitch not in diffusion.stages
    assert diffusion.stitch_steps == DEFAULT_STITCH_STEPS


@pytest.mark.parametrize("k", [0, 2])
@pytest.mark.parametrize("n", [5, 10])  # 10: longer than the 3-step planning interval
def test_replan_blends_into_the_executed_plan(tiny_meanflow, tiny_normalizer, closed_loop, k, n):
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    policy = _adversary(models, stitch_steps=n, k=k)
    env, emitted = closed_loop(policy, 3)  # cycle 0 planned at step 0, 3 steps executed
    previous = policy.plan_actions.copy()
    view = env.view()
    policy.act(view)  # step 3: cycle 1
    rows = np.flatnonzero(policy.plan_mask & view.active)
    assert rows.size > 0 and policy.cycles == 2

    fresh = _adversary(models, stitch_steps=0, k=k)  # the same cycle-1 plans, unblended
    fresh.reset(view)
    _same_cycle(fresh, policy)
    fresh.plan(view)
    keep = np.arange(n, 0, -1)[:, None] / (n + 1.0)  # n/(n+1), ..., 1/(n+1)
    expected = fresh.plan_actions[rows].copy()
    expected[:, :n] = keep * previous[rows, 3 : 3 + n] + (1 - keep) * expected[:, :n]
    np.testing.assert_allclose(policy.plan_actions[rows], expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(policy.plan_actions[rows, n:], fresh.plan_actions[rows, n:])
    # The stored plans are what the actions do from the current state (same path).
    np.testing.assert_array_equal(
        policy.plans[rows], rollout(view.current[rows], policy.plan_actions[rows], policy.dynamics)
    )
    # The step into the new plan moves the action 1/(n+1) of the unblended switch.
    switch = np.abs(fresh.plan_actions[rows, 0] - previous[rows, 3])
    np.testing.assert_allclose(
        np.abs(policy.plan_actions[rows, 0] - previous[rows, 3]), switch / (n + 1), atol=1e-12
    )
    unguided = rows[~policy.controllable[rows]]
    np.testing.assert_array_equal(policy.base_plans[unguided], policy.plans[unguided])
    base_actions = policy.state.base_actions
    np.testing.assert_array_equal(base_actions[unguided], policy.plan_actions[unguided])
    # every row's unguided alternative is what its actions do (the guided rows' blended
    # from their own base actions)
    np.testing.assert_array_equal(
        policy.base_plans[rows], rollout(view.current[rows], base_actions[rows], policy.dynamics)
    )
    guided = rows[policy.controllable[rows]]
    if k > 0:
        assert guided.size > 0
        assert not np.allclose(base_actions[guided], policy.plan_actions[guided])


def test_blending_first_blends_the_base_plans_into_the_executed_ones(
    tiny_meanflow, tiny_normalizer, closed_loop
):
    """Unguided, no avoidance steps, no holding: a new plan's first actions are the blend
    of the executed plan's continuation and the unblended plan (where that lies inside
    the action bounds, so the clip of the decoded plan does not act; to float rounding:
    the blend goes through the action normalisation); the later actions are the
    unblended plan's."""
    n = 10
    options = dict(
        k=0, planning_interval=0.3, seed=2, avoid_steps=0, hold_distance=0.0,
        generator=tiny_meanflow, normalizer=tiny_normalizer,
    )  # fmt: skip
    policy = RiskFlowAdversary(stitch_steps=n, **options)
    env, _ = closed_loop(policy, 3)  # cycle 0 planned at step 0, 3 steps executed
    view = env.view()
    rows = np.flatnonzero(policy.plan_mask & view.active)
    old, share = continuation(policy.state, view, rows, 52, policy.stitch_steps)
    np.testing.assert_allclose(share, np.broadcast_to(blend_share(n), share.shape))
    np.testing.assert_array_equal(old, policy.plan_actions[rows, 3 : 3 + n])
    policy.act(view)  # step 3: cycle 1
    fresh = RiskFlowAdversary(stitch_steps=0, **options)  # the same cycle-1 plans, unblended
    fresh.reset(view)
    _same_cycle(fresh, policy)
    fresh.plan(view)
    unblended = fresh.plan_actions[rows]
    dynamics = policy.dynamics
    low = np.array([dynamics.accel_min, -dynamics.yaw_rate_max])
    high = np.array([dynamics.accel_max, dynamics.yaw_rate_max])
    inside = (unblended[:, :n] > low) & (unblended[:, :n] < high)
    assert inside.mean() > 0.5
    expected = share[..., None] * old + (1 - share[..., None]) * unblended[:, :n]
    blended = policy.plan_actions[rows, :n]
    np.testing.assert_allclose(blended[inside], expected[inside], rtol=0, atol=1e-5)
    np.testing.assert_allclose(policy.plan_actions[rows, n:], unblended[:, n:], atol=1e-5)


def test_blending_first_blends_the_avoidance_corrections_of_the_first_action(
    tiny_meanflow, tiny_normalizer, closed_loop
):
    """The avoidance steps' gain: half of the first action's correction reaches the plan
    of a vehicle with a plan to continue (``CORRECTION_STITCH_STEPS`` = 1), all of every
    other step's and of vehicles without one."""
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    policy = RiskFlowAdversary(k=0, planning_interval=0.3, seed=2, **models)
    env, _ = closed_loop(policy, 3)
    view = env.view()
    slots = np.arange(policy.plan_mask.shape[0])
    continued = policy.plan_mask & view.active
    assert continued.any()
    u0 = torch.zeros(1, slots.size + 1, 52, 2, dtype=torch.float64)  # a padded row
    plans = PlanSet(
        [view], [policy.state], view.map, SimpleNamespace(slots=[slots]),
        eps=torch.zeros_like(u0), u=u0,
    )  # fmt: skip
    gain = stages.stitch(policy, plans).gain
    expected = np.ones(gain.shape)
    expected[0, : slots.size][continued, 0] = 1.0 - blend_share(CORRECTION_STITCH_STEPS)[0]
    np.testing.assert_array_equal(gain.numpy(), expected)
    assert CORRECTION_STITCH_STEPS == 1 and expected.min() == 0.5


def test_planning_passes_the_correction_gain_to_the_avoidance_steps(
    tiny_meanflow, tiny_normalizer, closed_loop
):
    """A re-plan blending first hands the ``stitch`` stage's gain to the avoidance steps;
    a cycle without that stage hands None (every correction whole)."""
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    for first in (True, False):
        policy = RiskFlowAdversary(k=0, planning_interval=0.3, seed=2, avoid_steps=2, **models)
        gains = []

        def spy(policy, plans, gains=gains):
            gains.append(plans.gain)
            return stages.avoid(policy, plans)

        cycle = [spy if stage is stages.avoid else stage for stage in policy.stages]
        policy.stages = tuple(s for s in cycle if first or s is not stages.stitch)
        closed_loop(policy, 4)  # cycles at steps 0 and 3
        assert len(gains) == 2
        if first:
            assert gains[1] is not None and float(gains[1].min()) == 0.5
        else:
            assert gains == [None, None]


def test_continuation_is_none_before_the_first_plan(tiny_meanflow, tiny_normalizer, closed_loop):
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    policy = RiskFlowAdversary(k=0, **models)
    env, _ = closed_loop(policy, 0)
    assert continuation(policy.state, env.view(), np.arange(2), 52, policy.stitch_steps) is None
