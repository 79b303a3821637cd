"""One-step sampling: determinism, shapes, consistency with the dynamics, num_samples."""

from __future__ import annotations

import pytest
import torch

from policies.learned.sampler import base_velocity, sample
from policies.learned.synthetic import synthetic_batch
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout

B, A, T = 2, 6, 52


@pytest.fixture
def setup(make_model):
    return make_model(seed=1), synthetic_batch(B, A, seed=2)


def _eps(*lead, seed=0):
    return torch.randn((*lead, T, 2), generator=torch.Generator().manual_seed(seed))


def test_sampling_is_deterministic_for_a_fixed_eps(setup, normalizer):
    model, batch = setup
    eps = _eps(B, A)
    actions, trajectories = sample(model, batch, eps, normalizer)
    again = sample(model, batch, eps.clone(), normalizer)
    assert torch.equal(actions, again[0]) and torch.equal(trajectories, again[1])
    other, _ = sample(model, batch, _eps(B, A, seed=1), normalizer)
    assert not torch.equal(actions, other)


def test_plans_are_one_step_and_consistent_with_the_dynamics(setup, normalizer):
    model, batch = setup
    eps = _eps(B, A)
    actions, trajectories = sample(model, batch, eps, normalizer)
    assert actions.shape == (B, A, T, 2) and trajectories.shape == (B, A, T, 4)
    scene = model.encode(batch)
    with torch.no_grad():
        expected = normalizer.denormalize(eps + base_velocity(model, eps, scene))
    live = batch.agent_mask
    bounds = DEFAULT_CONFIG
    assert bool(
        (actions[..., 0] >= bounds.accel_min).all() and (actions[..., 0] <= bounds.accel_max).all()
    )
    assert bool((actions[..., 1].abs() <= bounds.yaw_rate_max).all())
    inside = (expected[..., 0] > bounds.accel_min) & (expected[..., 0] < bounds.accel_max)
    inside &= expected[..., 1].abs() < bounds.yaw_rate_max
    inside &= live[..., None]
    torch.testing.assert_close(actions[inside], expected[inside])
    assert not actions[~live].any(), "padded agents get zero actions"
    torch.testing.assert_close(trajectories, rollout(batch.history[:, :, -1], actions))
    # A SceneContext works in place of the batch.
    from_scene, _ = sample(model, scene, eps, normalizer)
    torch.testing.assert_close(from_scene, actions)


def test_num_samples_batches_the_samples(setup, normalizer):
    model, batch = setup
    eps = _eps(B, 3, A)
    actions, trajectories = sample(model, batch, eps, normalizer, num_samples=3)
    assert actions.shape == (B, 3, A, T, 2) and trajectories.shape == (B, 3, A, T, 4)
    for k in range(3):
        single, single_traj = sample(model, batch, eps[:, k].contiguous(), normalizer)
        torch.testing.assert_close(actions[:, k], single, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(trajectories[:, k], single_traj, rtol=1e-5, atol=1e-4)
    assert not torch.allclose(actions[:, 0], actions[:, 1])


def test_noise_drawn_from_a_seeded_generator_is_reproducible(setup, normalizer):
    model, batch = setup

    def draw(seed):
        gen = torch.Generator().manual_seed(seed)
        return sample(model, batch, None, normalizer, num_samples=2, generator=gen)[0]

    assert torch.equal(draw(5), draw(5))
    assert draw(5).shape == (B, 2, A, T, 2)


def test_wrong_noise_shape_is_rejected(setup, normalizer):
    model, batch = setup
    with pytest.raises(ValueError, match=r"eps must have shape \(B, N, A, T, 2\)"):
        sample(model, batch, _eps(B, A), normalizer, num_samples=2)
    with pytest.raises(ValueError, match=r"eps must have shape \(B, A, T, 2\)"):
        sample(model, batch, _eps(B, A - 1), normalizer)
