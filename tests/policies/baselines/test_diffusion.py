"""Diffusion denoiser, training objective and guided chains (tiny models, synthetic scenes)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from policies.baselines.diffusion.guided import (
    DiffusionGuidanceConfig,
    SceneGeometry,
    guided_sample,
)
from policies.baselines.diffusion.model import DiffusionConfig, DiffusionDenoiser
from policies.baselines.diffusion.objective import diffusion_loss, draw_levels
from policies.baselines.diffusion.sampling import (
    OneCallSampler,
    chain_noise,
    reverse_chain,
)
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.guidance_losses import adversarial_loss
from policies.learned.plan_overlap import pair_separation
from policies.learned.sampler import decode_plans, sample
from policies.learned.synthetic import synthetic_batch
from policies.learned.validation import evaluate
from policies.learned.window_types import FUTURE_FIELDS

TINY = ModelConfig(
    encoder_dim=16, head_dim=32, context_dim=32, edge_dim=8, num_heads=2, encoder_layers=1,
    head_layers=1, map_widths=(4, 8), time_frequencies=8,
)  # fmt: skip
NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.03))


def tiny_denoiser(prediction: str = "v", seed: int = 0, scale: float = 0.2):
    """A tiny denoiser with perturbed weights (the adaLN-Zero head starts at 0)."""
    torch.manual_seed(seed)
    network = RiskFlowGenerator(TINY)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in network.parameters():
            param.add_(scale * torch.randn(param.shape, generator=gen))
    return DiffusionDenoiser(network, DiffusionConfig(prediction=prediction))


@pytest.fixture(autouse=True)
def one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.mark.parametrize("prediction", ["v", "sample", "epsilon"])
def test_denoiser_estimates_are_consistent(prediction):
    denoiser = tiny_denoiser(prediction)
    batch = synthetic_batch(2, 6, seed=1)
    scene = denoiser.encode(batch)
    x_k = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(0))
    k = torch.tensor([3, 80])
    x0_hat, eps_hat = denoiser(x_k, k, scene)
    torch.testing.assert_close(denoiser.schedule.q_sample(x0_hat, k, eps_hat), x_k)
    padded = ~scene.agent_mask
    if prediction == "sample":
        assert bool((x0_hat[padded] == 0).all())
    assert x0_hat.shape == x_k.shape and bool(torch.isfinite(x0_hat).all())
    torch.testing.assert_close(denoiser.level_time(torch.tensor(99.0)), torch.tensor(0.0))


@pytest.mark.parametrize("prediction", ["v", "epsilon"])
def test_training_lowers_the_loss_on_a_synthetic_batch(prediction):
    denoiser = tiny_denoiser(prediction, scale=0.0)
    batch = synthetic_batch(4, 6, seed=2)
    gen = torch.Generator().manual_seed(5)
    probes = [
        (torch.randn(batch.actions.shape, generator=gen), draw_levels(4, 100, gen, "cpu"))
        for _ in range(8)
    ]

    def probe_loss() -> float:
        with torch.no_grad():
            return sum(float(diffusion_loss(denoiser, batch, NORMALIZER, *p)[0]) for p in probes)

    before = probe_loss()
    optimizer = torch.optim.Adam(denoiser.network.parameters(), lr=3e-3)
    for _ in range(120):
        eps = torch.randn(batch.actions.shape, generator=gen)
        loss, metrics = diffusion_loss(
            denoiser, batch, NORMALIZER, eps, draw_levels(4, 100, gen, "cpu")
        )
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert {"loss", "action_mse", "eps_mse", "ade", "position_mse"} <= set(metrics)
    assert probe_loss() < 0.8 * before


def test_loss_checks_its_inputs():
    denoiser = tiny_denoiser()
    batch = synthetic_batch(2, 4)
    eps = torch.zeros(batch.actions.shape)
    with pytest.raises(ValueError, match="levels"):
        diffusion_loss(denoiser, batch, NORMALIZER, eps, torch.tensor([0, 100]))
    with pytest.raises(ValueError, match="eps"):
        diffusion_loss(denoiser, batch, NORMALIZER, eps[:, :1], torch.tensor([0, 1]))
    live = dataclasses.replace(batch, **dict.fromkeys(FUTURE_FIELDS))
    with pytest.raises(ValueError, match="future fields"):
        diffusion_loss(denoiser, live, NORMALIZER, eps, torch.tensor([0, 1]))


def test_one_call_sampler_serves_the_riskflow_sampler_and_validation():
    denoiser = tiny_denoiser()
    batch = synthetic_batch(2, 5, seed=3)
    one_call = OneCallSampler(denoiser, sampling_steps=4)
    eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(1))
    actions, trajectories = sample(one_call, batch, eps, NORMALIZER)
    scene = denoiser.encode(batch)
    noise = torch.zeros((5, *eps.shape))
    noise[0] = eps
    x0 = reverse_chain(denoiser, scene, noise, denoiser.schedule.levels(4), eta=0.0)[-1]
    expected, _ = decode_plans(x0, scene.state, scene.agent_mask, NORMALIZER)
    torch.testing.assert_close(actions, expected)
    metrics = evaluate(one_call, [batch], NORMALIZER, num_samples=2)
    assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())
    assert metrics["agents"] > 0


def scene_problem(seed: int = 4, agents: int = 6):
    """A tiny denoiser, one synthetic scene, its context and geometry (no map)."""
    denoiser = tiny_denoiser(seed=seed)
    batch = synthetic_batch(1, agents, seed=seed)
    scene = denoiser.encode(batch)
    geometry = SceneGeometry(
        state=scene.state[0], length=batch.length[0], width=batch.width[0],
        agent_mask=scene.agent_mask[0], drivable_map=None, frame=torch.zeros(3),
    )  # fmt: skip
    return denoiser, scene, geometry


@pytest.mark.parametrize(
    ("gradient", "steps", "anchor"),
    [("mean", None, True), ("clean", None, True), ("mean", 8, True), ("clean", 8, False)],
)
def test_guidance_moves_only_the_controllable_agents_and_lowers_l_adv(gradient, steps, anchor):
    denoiser, scene, geometry = scene_problem()
    levels = denoiser.schedule.levels(steps)
    noise = chain_noise((1, 6, 52, 2), levels, torch.Generator().manual_seed(7))
    controllable = torch.tensor([True, False, True, False, True, False])  # the ego is ignored
    config = DiffusionGuidanceConfig(gradient=gradient, step_size=0.3, anchor=anchor)
    result = guided_sample(
        denoiser, scene, noise, levels, geometry, controllable, NORMALIZER, config
    )
    base, base_trajectories = decode_plans(
        reverse_chain(denoiser, scene, noise, levels)[-1][0], geometry.state,
        geometry.agent_mask, NORMALIZER,
    )  # fmt: skip
    rows, others = torch.tensor([2, 4]), torch.tensor([0, 1, 3, 5])
    if anchor:
        torch.testing.assert_close(result.base_actions, base, rtol=0, atol=0)
        assert torch.equal(result.actions[others], base[others])
        assert torch.equal(result.trajectories[others], result.base_trajectories[others])
    else:  # one chain: the others react, there are no separate base plans
        assert torch.equal(result.base_actions, result.actions)
    assert not torch.allclose(result.actions[rows], base[rows])
    target = result.trajectories[others, :, :2]
    guided = adversarial_loss(result.trajectories[rows, :, :2], target)
    unguided = adversarial_loss(base_trajectories[rows, :, :2], base_trajectories[others, :, :2])
    assert float(guided) < 0.9 * float(unguided)
    assert result.losses.shape == (len(levels) + 1, 2)
    torch.testing.assert_close(result.losses[-1, 0], guided)


@pytest.mark.parametrize("gradient", ["mean", "clean"])
def test_separation_term_keeps_the_guided_vehicles_apart(gradient):
    """Two guided cars in the outer lanes closing on the ego ahead (RiskFlow's test of the
    same term): without ``L_sep`` their guided boxes overlap near the ego; with it they
    overlap far less, and they still close on the ego."""
    denoiser, scene, geometry = scene_problem(agents=4)
    ego, left, right, behind = [30, 0, 8, 0], [0, 3.5, 14, 0], [0, -3.5, 14, 0], [-40, 3.5, 10, 0]
    state = [ego, left, right, behind]
    geometry = dataclasses.replace(
        geometry, state=torch.tensor(state, dtype=torch.float32), length=torch.full((4,), 4.5),
        width=torch.full((4,), 1.8),
    )  # fmt: skip
    levels, rows = denoiser.schedule.levels(8), [1, 2]
    controllable = torch.tensor([False, True, True, False])
    penetration, adversarial = [], []
    for weight in (0.0, 20.0):
        noise = chain_noise((1, 4, 52, 2), levels, torch.Generator().manual_seed(7))
        config = DiffusionGuidanceConfig(
            gradient=gradient, target="ego", step_size=0.3, lambda_sep=weight, horizon=52
        )  # over the whole plan, as RiskFlow's test
        result = guided_sample(
            denoiser, scene, noise, levels, geometry, controllable, NORMALIZER, config
        )
        gaps = pair_separation(
            result.trajectories[None, rows], geometry.length[None, rows],
            geometry.width[None, rows],
        )[0, 0, 1]  # fmt: skip
        penetration.append(float(torch.relu(-gaps).square().sum()))
        adversarial.append(float(result.losses[-1, 0]))
    assert penetration[0] > 10.0 and penetration[1] < 0.1 * penetration[0]
    assert max(adversarial) < 0.9 * float(result.losses[0, 0])


def test_no_controllable_agent_is_the_unguided_chain_and_seeds_repeat():
    denoiser, scene, geometry = scene_problem(seed=5)
    levels = denoiser.schedule.levels(6)
    controllable = torch.tensor([False, True, True, False, False, False])
    runs = []
    for anchor in (True, True, False):
        noise = chain_noise((1, 6, 52, 2), levels, torch.Generator().manual_seed(9))
        config = DiffusionGuidanceConfig(anchor=anchor)
        nobody = torch.zeros(6, dtype=torch.bool)
        none = guided_sample(denoiser, scene, noise, levels, geometry, nobody, NORMALIZER, config)
        unguided, _ = decode_plans(
            reverse_chain(denoiser, scene, noise, levels)[-1][0], geometry.state,
            geometry.agent_mask, NORMALIZER,
        )  # fmt: skip
        assert torch.equal(none.actions, unguided) and none.losses.numel() == 0
        runs.append(
            guided_sample(
                denoiser, scene, noise, levels, geometry, controllable, NORMALIZER, config
            )
        )
    assert torch.equal(runs[0].actions, runs[1].actions)
    assert torch.equal(runs[0].losses, runs[1].losses)
    assert not torch.equal(runs[0].actions, runs[2].actions)


def test_standing_agents_stand_still_and_are_never_guided():
    denoiser, scene, geometry = scene_problem(seed=6)
    standing = torch.tensor([False, True, False, False, False, False])
    geometry = dataclasses.replace(geometry, standing=standing)
    levels = denoiser.schedule.levels(4)
    noise = chain_noise((1, 6, 52, 2), levels, torch.Generator().manual_seed(1))
    result = guided_sample(
        denoiser, scene, noise, levels, geometry, torch.ones(6, dtype=torch.bool), NORMALIZER
    )
    assert bool((result.actions[1] == 0).all())
    still = geometry.state[1].clone()
    still[2] = 0.0
    torch.testing.assert_close(result.trajectories[1], still.expand(52, 4))


def test_guidance_config_is_checked():
    with pytest.raises(ValueError, match="gradient"):
        DiffusionGuidanceConfig(gradient="score")
    with pytest.raises(ValueError, match="inner_steps 1"):
        DiffusionGuidanceConfig(gradient="clean", inner_steps=3)
    with pytest.raises(ValueError, match="step_size"):
        DiffusionGuidanceConfig(step_size=0.0)
    with pytest.raises(ValueError, match="lambda_sep"):
        DiffusionGuidanceConfig(lambda_sep=-1.0)
    with pytest.raises(ValueError, match="prediction"):
        DiffusionConfig(prediction="velocity")


def test_with_target_ego_the_attacker_keeps_clear_of_a_parked_bystander():
    """Anchored, target ``ego``: the bystanders' base plans are fixed and ``L_sep`` keeps
    the attacker off them as RiskFlow's does (a car parked on the attacker's way to the
    ego); without the term the attacker drives through it."""
    denoiser, scene, geometry = scene_problem(agents=3)
    ego, attacker, parked = [30, 0, 8, 0], [0, 0, 14, 0], [14, 0.5, 0, 0]
    geometry = dataclasses.replace(
        geometry, state=torch.tensor([ego, attacker, parked], dtype=torch.float32),
        length=torch.full((3,), 4.5), width=torch.full((3,), 1.8),
        standing=torch.tensor([False, False, True]),
    )  # fmt: skip
    levels = denoiser.schedule.levels(8)
    controllable = torch.tensor([False, True, False])
    penetration = []
    for weight in (0.0, 20.0):
        noise = chain_noise((1, 3, 52, 2), levels, torch.Generator().manual_seed(7))
        config = DiffusionGuidanceConfig(target="ego", step_size=0.3, lambda_sep=weight)
        result = guided_sample(
            denoiser, scene, noise, levels, geometry, controllable, NORMALIZER, config
        )
        gaps = pair_separation(
            result.trajectories[None, 1:], geometry.length[None, 1:], geometry.width[None, 1:]
        )[0, 0, 1]
        penetration.append(float(torch.relu(-gaps).square().sum()))
    assert penetration[0] > 1.0 and penetration[1] < 0.5 * penetration[0], penetration
