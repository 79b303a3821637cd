"""Validation metrics: closed-form displacement errors, constant velocity, determinism."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from policies.learned.synthetic import synthetic_batch
from policies.learned.validation import METRICS, displacement_errors, evaluate


def test_displacement_errors_closed_form():
    steps = 5
    future = torch.zeros(1, 3, steps, 4)
    predicted = future.clone()
    predicted[..., 0] = torch.arange(1, steps + 1, dtype=torch.float32)  # error k + 1 at step k
    valid = torch.ones(1, 3, steps, dtype=torch.bool)
    valid[0, 1, 3:] = False  # agent 1: steps 0..2 observed
    valid[0, 2] = False  # agent 2: nothing observed
    agent_mask = torch.tensor([[True, True, True]])
    ade, fde, has = displacement_errors(predicted, future, valid, agent_mask)
    torch.testing.assert_close(ade, torch.tensor([[3.0, 2.0, 0.0]]))
    torch.testing.assert_close(fde, torch.tensor([[5.0, 3.0, 0.0]]))
    assert has.tolist() == [[True, True, False]]
    many = torch.stack([predicted, 2 * predicted], dim=1)  # (B, N, A, T, 4)
    ade_n, fde_n, _ = displacement_errors(many, future, valid, agent_mask)
    torch.testing.assert_close(ade_n, torch.tensor([[[3.0, 2.0, 0.0], [6.0, 4.0, 0.0]]]))
    torch.testing.assert_close(fde_n[:, 1], 2 * fde)


def test_evaluate_is_deterministic_and_measures_constant_velocity(
    make_model, normalizer, tiny_config
):
    model = make_model(tiny_config, randomize=False).eval()  # u = 0: plans are the noise
    batches = [synthetic_batch(2, 4, seed=s) for s in (0, 1)]
    first = evaluate(model, batches, normalizer, num_samples=3, seed=5)
    assert set(METRICS) <= set(first) and first["windows"] == 4
    assert first == evaluate(model, batches, normalizer, num_samples=3, seed=5)
    assert first != evaluate(model, batches, normalizer, num_samples=3, seed=6)
    assert first["min_ade"] < first["ade"]  # best of 3 noise plans beats a typical one
    assert first["jerk_rms"] > 10 * first["data_jerk_rms"]  # noise is far from smooth
    assert first["jerk_median"] > 10 * first["data_jerk_median"]
    # constant velocity on data that keeps its speed and heading: zero error
    still = [
        dataclasses.replace(
            b, actions=torch.zeros_like(b.actions), future=_constant_velocity_future(b)
        )
        for b in batches
    ]
    metrics = evaluate(model, still, normalizer, num_samples=2)
    assert metrics["cv_ade"] == pytest.approx(0.0, abs=1e-4)
    assert metrics["data_jerk_rms"] == 0.0 and math.isfinite(metrics["ade"])
    # One change of the logged acceleration per plan: the RMS sees it, the median does not.
    steps = still[0].actions.shape[2]
    braking = [
        dataclasses.replace(
            b, actions=b.actions.index_fill(2, torch.arange(steps // 2, steps), -1.0)
        )
        for b in still
    ]
    metrics = evaluate(model, braking, normalizer, num_samples=2)
    assert metrics["data_jerk_rms"] > 0.0 and metrics["data_jerk_median"] == 0.0


def _constant_velocity_future(batch):
    from riskflow_env.dynamics import rollout

    state = batch.history[:, :, -1]
    return rollout(state, torch.zeros_like(batch.actions))
