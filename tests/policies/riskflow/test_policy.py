"""RiskFlowAdversary in closed loop: schedule, plan buffer, K=0, seeding, bounds, done agents."""

from __future__ import annotations

import dataclasses
from importlib import resources

import numpy as np
import pytest
import torch

from policies.learned.sampler import sample
from policies.learned.window_types import collate_windows
from policies.learned.windows import window_from_view
from policies.riskflow.policy import PHASES, RiskFlowAdversary
from riskflow_env.dynamics import DEFAULT_CONFIG
from riskflow_env.scenarios import Scenario
from riskflow_env.view import ScenePolicy
from tests.policies.straight_road import (
    ROAD_ENV,
    TINY_NORMALIZER,
    make_road_scenario,
    road_env,
    run_closed_loop,
)

NORMALIZER = TINY_NORMALIZER
CONFIG = dataclasses.replace(ROAD_ENV, max_agents=9, episode_steps=25)
FAR = (230.0, 0.0)  # beyond WindowConfig.max_distance (150 m): no window slot
CRASH = [(60.0, -3.5), (61.0, -3.5)]  # two overlapping cars: done at the first step
make_scenario = make_road_scenario


@pytest.fixture
def model(make_model, tiny_config):
    return make_model(tiny_config, seed=1).eval()


def adversary(model, **kwargs) -> RiskFlowAdversary:
    kwargs = {"k": 2, "guidance_steps": 5, "seed": 3, "threads": 1, **kwargs}
    return RiskFlowAdversary(generator=model, normalizer=NORMALIZER, **kwargs)


def run(policy: RiskFlowAdversary, scenario: Scenario, steps: int, hook=None):
    """Closed loop with the ego holding speed; returns the env and the emitted actions."""

    def check(view, policy, actions):
        assert set(actions) == set(view.live_agents) - {"ego"}
        if hook is not None:
            hook(view, policy, actions)

    return run_closed_loop(policy, steps, scenario, CONFIG, check)


def test_is_a_scene_policy(model):
    assert isinstance(adversary(model), ScenePolicy)


@pytest.mark.parametrize(("interval", "cycles"), [(0.5, 5), (0.2, 12), (0.1, 23)])
def test_replans_on_schedule(model, interval, cycles):
    planned_at = []

    def record(view, policy, actions):
        if policy.cycles > len(planned_at):
            planned_at.append(view.step)

    policy = adversary(model, planning_interval=interval, guidance_steps=1)
    run(policy, make_scenario(), 23, record)
    assert policy.cycles == cycles
    every = round(interval / 0.1)
    assert planned_at == list(range(0, 23, every))


def test_each_step_emits_the_next_action_of_the_plan(model):
    policy = adversary(model)
    checked = []

    def check(view, policy, actions):
        elapsed = view.step % 5
        for name, action in actions.items():
            slot = view.slot(name)
            np.testing.assert_array_equal(action, policy.plan_actions[slot, elapsed])
        checked.append(view.step)

    env, _ = run(policy, make_scenario(), 8, check)
    assert checked == list(range(8))
    # Closed loop: the vehicles drove the plans of the last cycle (planned at step 5).
    driven = policy.plan_mask.copy()
    driven[0] = False  # the ego held its speed
    plans = policy.plans[driven, 2]  # state after 3 plan steps (step 8)
    np.testing.assert_allclose(env.scene.current[driven], plans, atol=2e-3)


def test_k0_gives_exactly_the_unguided_generator(model):
    policy = adversary(model, k=0, guidance_steps=30)
    env = road_env(CONFIG)
    policy.reset(env.view())
    policy.plan(env.view())
    assert not policy.controllable.any()
    np.testing.assert_array_equal(policy.plans, policy.base_plans)
    window = window_from_view(env.view(), policy.window_config)
    batch = collate_windows([window])
    actions, _ = sample(model, batch, policy.noise[None], NORMALIZER)
    slots = window.agent_index
    # A different code path from the policy's (batch layout, op order), in float32: actions
    # of a few m/s^2 round at about 8 * 2**-24 = 5e-7 per op, so allow 1e-5.
    np.testing.assert_allclose(policy.plan_actions[slots], actions[0].numpy(), rtol=0, atol=1e-5)


def test_guidance_changes_only_the_controllable_vehicles(model):
    policy = adversary(model, k=2, guidance_steps=10)
    env = road_env(CONFIG)
    policy.reset(env.view())
    plans = policy.plan(env.view())
    assert policy.controllable.sum() == 2 and not policy.controllable[0]
    assert policy.controllable_names == tuple(
        env.possible_agents[i] for i in np.flatnonzero(policy.controllable)
    )
    same = policy.plan_mask & ~policy.controllable
    np.testing.assert_array_equal(plans[same], policy.base_plans[same])
    assert not np.allclose(plans[policy.controllable], policy.base_plans[policy.controllable])
    assert set(policy.timings) == {*PHASES, "total"}
    assert policy.guidance_losses.shape == (11, 2)


@pytest.mark.reliability
def test_same_seed_same_closed_loop_rollout(model):
    histories = []
    for seed in (11, 11, 12):
        env, _ = run(adversary(model, seed=seed), make_scenario(), 12)
        histories.append(env.scene.history.copy())
    np.testing.assert_array_equal(histories[0], histories[1])
    assert not np.array_equal(histories[0], histories[2])


def test_actions_within_bounds(model):
    policy = adversary(model, k="all", optimizer="gradient", step_size=5.0)
    _, emitted = run(policy, make_scenario(), 10)
    actions = np.array([a for step in emitted for a in step.values()])
    assert actions[:, 0].min() >= DEFAULT_CONFIG.accel_min
    assert actions[:, 0].max() <= DEFAULT_CONFIG.accel_max
    assert np.abs(actions[:, 1]).max() <= DEFAULT_CONFIG.yaw_rate_max


def test_done_vehicles_stand_still_and_far_vehicles_hold_speed(model):
    scenario = make_scenario([FAR, *CRASH])
    slots = {}

    def check(view, policy, actions):
        if not slots:
            rows = list(view.scenario_rows)
            slots.update(far=rows.index(6), crash=[rows.index(7), rows.index(8)])
        far, crash = slots["far"], slots["crash"]
        assert not policy.plan_mask[far] and np.isnan(policy.plans[far]).all()
        np.testing.assert_array_equal(actions[view.agent_names[far]], 0.0)  # hold speed
        if view.step >= 5:  # planned after the crash
            done = ~view.active & view.present
            assert done[crash].all()
            assert not (policy.controllable & done).any()
            assert policy.plan_mask[crash].all()  # still in the window, as obstacles
            np.testing.assert_allclose(policy.plans[crash, :, 2], 0.0)  # standing still
            np.testing.assert_allclose(
                policy.plans[crash, :, :2],
                np.repeat(view.current[crash, None, :2], 52, axis=1),
                atol=1e-3,
            )

    env, _ = run(adversary(model, k="all"), scenario, 12, check)
    assert env.scene.current[slots["far"], 2] == pytest.approx(12.0)


def test_draw_pushes_overlays(model):
    from riskflow_env.render import SceneRenderer

    policy = adversary(model)
    env = road_env(CONFIG)
    renderer = SceneRenderer("rgb_array")
    policy.draw(renderer)  # nothing planned yet: no overlay
    assert not renderer.overlays
    policy.reset(env.view())
    policy.plan(env.view())
    policy.draw(renderer)
    guided = renderer.overlays["riskflow_guided"]
    assert guided.trajectories.shape == (9, 52, 2)
    assert set(guided.highlight) == set(np.flatnonzero(policy.controllable).tolist())
    assert "riskflow_base" in renderer.overlays


def test_threads_are_restored(model):
    before = torch.get_num_threads()
    policy = adversary(model, threads=1)
    env = road_env(CONFIG)
    policy.reset(env.view())
    policy.plan(env.view())
    assert torch.get_num_threads() == before


def test_bad_options(model):
    with pytest.raises(ValueError, match="k must be"):
        adversary(model, k=-1)
    with pytest.raises(ValueError, match="normalizer"):
        RiskFlowAdversary(generator=model)
    with pytest.raises(ValueError, match="planning_interval"):
        adversary(model, planning_interval=0.0)
    with pytest.raises(ValueError, match="target must be one of"):
        adversary(model, target="everyone")
    env = road_env(CONFIG)
    with pytest.raises(RuntimeError, match="reset"):
        adversary(model).act(env.view())
    for interval in (0.25, 6.0):
        with pytest.raises(ValueError, match="multiple of dt"):
            adversary(model, planning_interval=interval).reset(env.view())


def test_default_loads_the_shipped_checkpoint_or_says_it_is_missing():
    shipped = resources.files("policies").joinpath("checkpoints", "riskflow_default.pt")
    if shipped.is_file():
        policy = RiskFlowAdversary()
        assert policy.normalizer is not None
    else:
        with pytest.raises(FileNotFoundError, match="checkpoint"):
            RiskFlowAdversary()
