"""Batched planning: B scenes in one call give each scene the plans it gets alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import riskflow_env
from policies.baselines.diffusion.policy import DiffusionAdversary
from policies.baselines.strive import StriveAdversary
from policies.pipeline.batched import BatchedAdversary
from policies.pipeline.stages import plan_scenes
from policies.riskflow.policy import RiskFlowAdversary
from riskflow_env.config import EnvConfig
from tests.policies.straight_scenes import make_scenario

CONFIG = EnvConfig(
    max_agents=9, episode_steps=30, terminate_on_collision="none", terminate_on_offroad="none"
)


def make_env(index: int):
    scenario = make_scenario(index)
    env = riskflow_env.parallel_env(config=CONFIG, scenarios=scenario)
    env.reset(seed=0, options={"scenario": scenario})
    return env


def riskflow(model, normalizer, strive=False, **kwargs) -> RiskFlowAdversary:
    options = {"k": 2, "guidance_steps": 6, "planning_interval": 0.3, "seed": 4, **kwargs}
    kind = StriveAdversary if strive else RiskFlowAdversary
    return kind(generator=model, normalizer=normalizer, **options)


def step(env, actions) -> None:
    if env.agents:
        env.step({**actions, "ego": np.array([0.3, 0.02])} if "ego" in env.agents else actions)


def close(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_allclose(a, b, rtol=0, atol=2e-4, equal_nan=True)


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"avoid_steps": 3, "hold_distance": 1.0},
        {"avoid_steps": 3, "stitch_steps": 8},
        {"optimizer": "gradient"},
        {"strive": True},  # STRIVE-style: one latent optimisation over the scenes' rows
        {"strive": True, "avoid_steps": 3},
    ],
)
def test_batched_plans_equal_planning_each_scene_alone(tiny_meanflow, tiny_normalizer, options):
    """Three scenes (own maps, 4, 5 and 7 agents: padded), scene 1 restarting at step 4
    (then re-planning on its own schedule): the batch plans what three one-scene policies
    with the same seeds plan, on the same views; the noise is the same bit for bit
    (avoidance steps, holding at rest and blending act on each scene as alone)."""
    seeds = [4, 11, 7]
    batch = BatchedAdversary(riskflow(tiny_meanflow, tiny_normalizer, **options), 3, seeds=seeds)
    alone = [riskflow(tiny_meanflow, tiny_normalizer, seed=seed, **options) for seed in seeds]
    envs = [make_env(index) for index in range(3)]
    batch.reset([env.view() for env in envs])
    for policy, env in zip(alone, envs, strict=True):
        policy.reset(env.view())
    planned, guided = [], 0
    for t in range(9):
        if t == 4:  # a new episode in scene 1 only
            scenario = make_scenario(1)
            envs[1].reset(seed=0, options={"scenario": scenario})
            batch.reset_scene(1, envs[1].view())
            alone[1].reset(envs[1].view())
        views = [env.view() for env in envs]
        expected = [policy.act(view) for policy, view in zip(alone, views, strict=True)]
        got = batch.act(views)
        planned.append(batch.last_planned)
        for b in range(3):
            assert got[b].keys() == expected[b].keys()
            for name in expected[b]:
                close(got[b][name], expected[b][name])
            mine, theirs = batch.scenes[b], alone[b]
            assert mine.cycles == theirs.cycles
            assert torch.equal(mine.noise, theirs.noise)
            np.testing.assert_array_equal(mine.controllable, theirs.controllable)
            close(mine.plans, theirs.plans)
            close(mine.base_plans, theirs.base_plans)
            close(mine.guidance_losses, theirs.guidance_losses)
            if options.get("strive"):
                close(mine.latent.numpy(), theirs.latent.numpy())
                close(mine.prior_losses, theirs.prior_losses)
            guided += int(mine.controllable.sum())
        for env, actions in zip(envs, expected, strict=True):
            step(env, actions)
    assert planned == [(0, 1, 2), (), (), (0, 1, 2), (1,), (), (0, 2), (1,), ()]
    assert guided > 0


def test_same_seeds_same_batched_rollout_bit_for_bit(tiny_meanflow, tiny_normalizer):
    def rollout():
        batch = BatchedAdversary(riskflow(tiny_meanflow, tiny_normalizer), 3)
        envs = [make_env(index) for index in range(3)]
        batch.reset([env.view() for env in envs])
        out = []
        for _ in range(4):
            actions = batch.act([env.view() for env in envs])
            out.append([np.stack(list(a.values())) for a in actions])
            for env, action in zip(envs, actions, strict=True):
                step(env, action)
        return out

    first, second = rollout(), rollout()
    for a, b in zip(first, second, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)


def test_a_scene_noise_does_not_depend_on_the_batch(tiny_meanflow, tiny_normalizer):
    """Scene seeds default to ``policy.seed + b``; a scene's noise is its own stream's."""
    envs = [make_env(index) for index in range(3)]
    views = [env.view() for env in envs]
    batch = BatchedAdversary(riskflow(tiny_meanflow, tiny_normalizer, seed=4), 3)
    batch.reset(views)
    batch.plan(views)
    single = BatchedAdversary(riskflow(tiny_meanflow, tiny_normalizer, seed=6), 1)
    single.reset(views[2:])
    single.plan(views[2:])
    assert torch.equal(batch.scenes[2].noise, single.scenes[0].noise)
    assert batch.scenes[0].timings.keys() == batch.scenes[2].timings.keys()


@pytest.mark.parametrize("kind", ["strive", "diffusion"])
def test_other_adversaries_take_the_batched_call(
    kind, tiny_meanflow, tiny_denoiser, tiny_normalizer
):
    """STRIVE-style and the diffusion baselines take the batched call and plan what they
    plan alone."""
    options = {"k": 1, "planning_interval": 0.3, "seed": 2}
    if kind == "strive":
        make = lambda seed: StriveAdversary(  # noqa: E731
            generator=tiny_meanflow, normalizer=tiny_normalizer, guidance_steps=2,
            **{**options, "seed": seed},
        )  # fmt: skip
    else:
        make = lambda seed: DiffusionAdversary(  # noqa: E731
            denoiser=tiny_denoiser, normalizer=tiny_normalizer, sampling_steps=3,
            **{**options, "seed": seed},
        )  # fmt: skip
    envs = [make_env(index) for index in range(2)]
    views = [env.view() for env in envs]
    batch = BatchedAdversary(make(2), 2)
    batch.reset(views)
    got = batch.act(views)
    for b, view in enumerate(views):
        alone = make(2 + b)
        alone.reset(view)
        expected = alone.act(view)
        for name in expected:
            close(got[b][name], expected[name])


def test_bad_input_names_the_argument(tiny_meanflow, tiny_normalizer):
    policy = riskflow(tiny_meanflow, tiny_normalizer)
    envs = [make_env(index) for index in range(2)]
    views = [env.view() for env in envs]
    with pytest.raises(ValueError, match="num_scenes"):
        BatchedAdversary(policy, 0)
    with pytest.raises(ValueError, match="seeds"):
        BatchedAdversary(policy, 2, seeds=[1])
    with pytest.raises(TypeError, match="policy"):
        BatchedAdversary(object(), 2)
    batch = BatchedAdversary(policy, 2)
    with pytest.raises(ValueError, match="views"):
        batch.reset(views[:1])
    with pytest.raises(RuntimeError, match="reset"):
        batch.act(views)
    batch.reset(views)
    with pytest.raises(ValueError, match="scenes"):
        batch.plan(views, [0, 0])
    with pytest.raises(ValueError, match="scenes"):
        batch.plan(views, [2])
    with pytest.raises(ValueError, match="index"):
        batch.reset_scene(5, views[0])
    other = riskflow(tiny_meanflow, tiny_normalizer)
    other.reset(views[1])
    with pytest.raises(ValueError, match="copies of one policy"):
        plan_scenes([batch.scenes[0], other], views)
    with pytest.raises(ValueError, match="equal length"):
        plan_scenes(batch.scenes, views[:1])


def test_act_array_is_act_as_one_array(tiny_meanflow, tiny_normalizer):
    """``act_array`` gives ``act``'s actions in their slots (zeros for the ego and empty
    slots), for batched stepping; the same seeds give the same actions."""
    envs = [make_env(index) for index in range(3)]
    views = [env.view() for env in envs]
    dicts, arrays = (BatchedAdversary(riskflow(tiny_meanflow, tiny_normalizer), 3) for _ in "ab")
    dicts.reset(views)
    arrays.reset(views)
    expected, got = dicts.act(views), arrays.act_array(views)
    assert got.shape == (3, CONFIG.max_agents, 2)
    for b, (actions, view) in enumerate(zip(expected, views, strict=True)):
        slots = [view.slot(agent) for agent in actions]
        np.testing.assert_array_equal(got[b, slots], np.stack(list(actions.values())))
        np.testing.assert_array_equal(np.delete(got[b], slots, axis=0), 0.0)


def test_act_array_leaves_ended_scenes_alone(tiny_meanflow, tiny_normalizer):
    """``running``: a scene whose episode is over is neither planned nor asked (zeros); the
    running ones get what they get without the mask (to float rounding: the batch is
    smaller); a bad mask names the argument."""
    envs = [make_env(index) for index in range(3)]
    views = [env.view() for env in envs]
    full, masked = (BatchedAdversary(riskflow(tiny_meanflow, tiny_normalizer), 3) for _ in "ab")
    full.reset(views)
    masked.reset(views)
    expected = full.act_array(views)
    got = masked.act_array(views, np.array([True, False, True]))
    assert masked.last_planned == (0, 2) and masked.scenes[1].cycles == 0
    np.testing.assert_array_equal(got[1], 0.0)
    close(got[[0, 2]], expected[[0, 2]])  # a batch of 2 scenes instead of 3: rounding
    with pytest.raises(ValueError, match="running"):
        masked.act_array(views, np.array([True, False]))


@pytest.mark.parametrize(
    "options",
    [
        {"variant": "ctg"},
        {"variant": "ctgpp"},
        {"variant": "ccdiff", "inner_steps": 2},
        {"variant": "ctgpp", "anchor": False, "target": "ego"},
        {"variant": "ctg", "anchor": False, "k": 0},
    ],
)
def test_diffusion_plans_every_scene_in_one_chain(
    tiny_denoiser, tiny_normalizer, options, monkeypatch
):
    """The diffusion baselines plan B scenes (4, 5 and 7 agents: padded) with one denoiser
    pass per level for all of them, over several re-planning cycles, and each scene gets
    the plans it gets alone (the same noise, bit for bit)."""
    options = {"k": 2, "planning_interval": 0.3, "sampling_steps": 3, **options}

    def make(seed):
        return DiffusionAdversary(
            denoiser=tiny_denoiser, normalizer=tiny_normalizer, seed=seed, **options
        )

    seeds = [3, 8, 5]
    batch = BatchedAdversary(make(seeds[0]), 3, seeds=seeds)
    alone = [make(seed) for seed in seeds]
    envs = [make_env(index) for index in range(3)]
    batch.reset([env.view() for env in envs])
    for policy, env in zip(alone, envs, strict=True):
        policy.reset(env.view())
    calls, cycles = [], 0
    network = tiny_denoiser.network
    velocity = network.average_velocity

    def counted(*args, **kwargs):
        calls.append(1)
        return velocity(*args, **kwargs)

    monkeypatch.setattr(network, "average_velocity", counted)
    for _ in range(7):
        views = [env.view() for env in envs]
        calls.clear()
        got = batch.act(views)
        batched_calls = len(calls)
        expected = [policy.act(view) for policy, view in zip(alone, views, strict=True)]
        if batched_calls:  # a planning step: one chain for all three scenes
            assert 3 * batched_calls == len(calls) - batched_calls
            cycles += 1
        for b, env in enumerate(envs):
            assert got[b].keys() == expected[b].keys()
            for name in expected[b]:
                close(got[b][name], expected[b][name])
            step(env, got[b])
        for b in range(3):
            assert torch.equal(batch.scenes[b].noise, alone[b].noise)
    assert cycles == 3  # at steps 0, 3 and 6
