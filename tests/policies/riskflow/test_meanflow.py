"""The MeanFlow JVP objective: derivative, identity, masking, stop-gradient, overfitting."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from policies.learned.sampler import base_velocity
from policies.learned.synthetic import synthetic_batch
from policies.learned.trajectory_loss import target_actions, trajectory_loss
from policies.learned.window_types import FUTURE_FIELDS, collate_windows
from policies.learned.windows import window_from_scenario
from policies.riskflow.meanflow import (
    DUDT_CLIP,
    OneStepFlowMatching,
    average_velocity_jvp,
    flow_matching_loss,
    meanflow_loss,
    meanflow_target,
)
from riskflow_env.scenarios import HighwayTrafficSource


def _times(batch_size: int, dtype: torch.dtype = torch.float32):
    t = torch.linspace(0.2, 0.5, batch_size, dtype=dtype)
    return t, t + 0.3


def test_jvp_matches_central_finite_difference_along_the_flow(make_model, normalizer):
    model = make_model(dtype=torch.float64)
    batch = synthetic_batch(2, 5, seed=3, dtype=torch.float64)
    scene = model.encode(batch)
    gen = torch.Generator().manual_seed(0)
    eps = torch.randn(batch.actions.shape, generator=gen, dtype=torch.float64)
    a_star = target_actions(batch, normalizer)
    t, r = _times(2, torch.float64)
    t_ = t[:, None, None, None]
    z_t, v = (1 - t_) * eps + t_ * a_star, a_star - eps

    def u_fn(z, t_in, r_in):
        return model.average_velocity(z, t_in, r_in, scene)

    u, dudt = average_velocity_jvp(u_fn, z_t, t, r, v)
    # time_scale = 1000 makes the sinusoids stiff in t (third derivative ~1e9): a small
    # step keeps the central difference's truncation error ~h^2 * 1e9 below 1e-6.
    h = 2e-8
    finite = (u_fn(z_t + h * v, t + h, r) - u_fn(z_t - h * v, t - h, r)) / (2 * h)
    torch.testing.assert_close(u, u_fn(z_t, t, r))
    assert dudt.abs().max() > 1e-3, "the perturbed model must have a non-trivial du/dt"
    torch.testing.assert_close(dudt, finite, rtol=1e-5, atol=1e-7)


def _closed_form_u(z, t, r, a=0.7, b=-1.3):
    """Average velocity of dz/dt = (a + b t) z from t to r: z (exp(Lambda) - 1) / (r - t)."""
    t_, r_ = t[:, None], r[:, None]
    growth = a * (r_ - t_) + 0.5 * b * (r_**2 - t_**2)
    return z * torch.expm1(growth) / (r_ - t_)


def test_meanflow_identity_target_on_a_closed_form_velocity_field():
    gen = torch.Generator().manual_seed(1)
    z = torch.randn(64, 3, generator=gen, dtype=torch.float64)
    t = 0.8 * torch.rand(64, generator=gen, dtype=torch.float64)
    r = t + 0.05 + (0.95 - t) * torch.rand(64, generator=gen, dtype=torch.float64)
    v = (0.7 - 1.3 * t)[:, None] * z  # the field's instantaneous velocity at (z, t)
    u, dudt = average_velocity_jvp(_closed_form_u, z, t, r, v)
    target = meanflow_target(v, dudt, t[:, None], r[:, None])
    torch.testing.assert_close(target, u, rtol=1e-10, atol=1e-12)
    # The instantaneous velocity is not the average one on this curved flow.
    assert (v - u).abs().max() > 0.1
    # r -> t: u tends to the instantaneous velocity, and so does the target.
    u_eq, dudt_eq = average_velocity_jvp(_closed_form_u, z, t, t + 1e-7, v)
    torch.testing.assert_close(u_eq, v, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(meanflow_target(v, dudt_eq, t[:, None], t[:, None]), v)


def test_loss_gradient_flows_through_u_only(make_model, normalizer):
    model = make_model()
    batch = synthetic_batch(2, 4, seed=0)
    eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(2))
    t, r = _times(2)
    loss, metrics = meanflow_loss(model, batch, normalizer, eps, t, r, clip=DUDT_CLIP)
    grads = torch.autograd.grad(loss, list(model.parameters()))

    # The same loss with du/dt precomputed as a constant has the same gradient.
    scene = model.encode(batch)
    a_star = target_actions(batch, normalizer)
    t_, r_ = t[:, None, None, None], r[:, None, None, None]
    z_t, v = (1 - t_) * eps + t_ * a_star, a_star - eps
    with torch.no_grad():
        _, dudt = average_velocity_jvp(
            lambda z, a, b: model.average_velocity(z, a, b, scene), z_t, t, r, v
        )
    dudt = dudt.clamp(-DUDT_CLIP, DUDT_CLIP)
    a_hat = eps + model.average_velocity(z_t, t, r, scene) + (t_ - r_) * dudt
    reference, _ = trajectory_loss(a_hat, batch, scene, normalizer)
    torch.testing.assert_close(loss, reference)
    for got, want in zip(
        grads, torch.autograd.grad(reference, list(model.parameters())), strict=True
    ):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)
    assert all(bool(g.abs().sum() > 0) for g in grads), "every parameter gets a gradient"
    assert set(metrics) >= {"loss", "position_mse", "ade", "fde", "action_mse", "dudt_clipped"}


def test_at_the_samplers_call_the_reconstruction_is_the_sampled_plan(make_model, normalizer):
    """(t, r) = (0, 1), the pairs of --one-step-fraction: z_t is the noise and, up to the
    clipped du/dt correction, a_hat is the plan the sampler makes from it."""
    model = make_model()
    batch = synthetic_batch(2, 4, seed=7)
    eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(3))
    t, r = torch.zeros(2), torch.ones(2)
    loss, _ = meanflow_loss(model, batch, normalizer, eps, t, r, clip=0.0)
    scene = model.encode(batch)
    plan = eps + base_velocity(model, eps, scene)  # what sampler.sample decodes
    reference, _ = trajectory_loss(plan, batch, scene, normalizer)
    torch.testing.assert_close(loss, reference)
    clipped = float(meanflow_loss(model, batch, normalizer, eps, t, r)[0].detach())
    assert math.isfinite(clipped) and clipped != float(loss.detach())


def test_loss_ignores_padded_agents_and_invalid_future_steps(make_model, normalizer):
    model = make_model()
    batch = synthetic_batch(2, 8, seed=4)
    assert not batch.agent_mask.all() and not batch.future_valid[batch.agent_mask].all()
    eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(0))
    t, r = _times(2)
    loss, _ = meanflow_loss(model, batch, normalizer, eps, t, r)
    ignored = ~(batch.future_valid & batch.agent_mask[..., None])
    changed = dataclasses.replace(batch, future=torch.where(ignored[..., None], 1e3, batch.future))
    loss_changed, _ = meanflow_loss(model, changed, normalizer, eps, t, r)
    torch.testing.assert_close(loss_changed, loss)


def test_flow_matching_loss_is_the_meanflow_loss_at_r_equal_t(make_model, normalizer):
    model = make_model()
    batch = synthetic_batch(3, 4, seed=5)
    eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(0))
    t = torch.tensor([0.1, 0.5, 0.9])
    loss_fm, _ = flow_matching_loss(model, batch, normalizer, eps, t)
    loss_mf, metrics = meanflow_loss(model, batch, normalizer, eps, t, t.clone())
    torch.testing.assert_close(loss_mf, loss_fm)
    assert math.isfinite(float(metrics["dudt_abs"]))


def test_loss_rejects_bad_times_and_noise(make_model, normalizer):
    model = make_model()
    batch = synthetic_batch(2, 3)
    eps = torch.zeros(batch.actions.shape)
    with pytest.raises(ValueError, match="t <= r"):
        meanflow_loss(
            model, batch, normalizer, eps, torch.tensor([0.5, 0.5]), torch.tensor([0.4, 0.6])
        )
    with pytest.raises(ValueError, match="eps must have the shape"):
        meanflow_loss(model, batch, normalizer, eps[:, :2], *_times(2))
    with pytest.raises(ValueError, match=r"t must be \(B,\)"):
        meanflow_loss(model, batch, normalizer, eps, torch.zeros(3), torch.ones(3))
    live = dataclasses.replace(batch, **dict.fromkeys(FUTURE_FIELDS))
    with pytest.raises(ValueError, match="future fields"):
        meanflow_loss(model, live, normalizer, eps, *_times(2))


@pytest.fixture
def one_thread():
    """Tiny models are op-overhead bound: one thread avoids oversubscribing shared CPUs."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.usefixtures("one_thread")
def test_overfitting_one_batch_drives_the_loss_down_by_orders_of_magnitude(make_model, normalizer):
    torch.manual_seed(0)
    model = make_model(randomize=False)
    batch = synthetic_batch(2, 4, seed=6)
    eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(0))
    t, r = torch.tensor([0.0, 0.3]), torch.tensor([0.7, 1.0])
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(250):
        loss, _ = meanflow_loss(model, batch, normalizer, eps, t, r)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert all(map(math.isfinite, losses))
    assert min(losses[-10:]) < 1e-2 * losses[0], (losses[0], losses[-10:])


def test_loss_runs_on_collated_recorded_windows(make_model, normalizer):
    scenario = HighwayTrafficSource().sample(np.random.default_rng(0))
    batch = collate_windows([window_from_scenario(scenario, k) for k in (30, 60)])
    model = make_model()
    eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(0))
    loss, metrics = meanflow_loss(model, batch, normalizer, eps, *_times(2))
    loss.backward()
    assert math.isfinite(float(loss)) and float(metrics["ade"]) > 0
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


def test_one_step_flow_matching_asks_for_the_instantaneous_velocity(make_model, tiny_config):
    model = make_model(tiny_config)
    calls = []

    def spy(z, t, r, scene):
        calls.append((t.clone(), r.clone()))
        return torch.zeros_like(z)

    model.average_velocity = spy
    adapter = OneStepFlowMatching(model)
    scene = model.encode(synthetic_batch(2, 3))
    t, r = torch.zeros(2), torch.ones(2)
    adapter.average_velocity(torch.zeros(2, 3, 52, 2), t, r, scene)
    torch.testing.assert_close(calls[0][1], t)
