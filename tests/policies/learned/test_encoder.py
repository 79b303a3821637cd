"""Scene encoder: own-frame histories, frame invariance, padding, input validation."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F

from policies.learned.encoder import history_features
from policies.learned.synthetic import synthetic_batch


def _rigid(batch, angle: float, shift: tuple[float, float]):
    """The same scenes in another frame (rotated by ``angle``, then translated)."""
    cos, sin = math.cos(angle), math.sin(angle)
    out = {}
    for key in ("history", "future"):
        s = getattr(batch, key)
        x = cos * s[..., 0] - sin * s[..., 1] + shift[0]
        y = sin * s[..., 0] + cos * s[..., 1] + shift[1]
        moved = torch.stack([x, y, s[..., 2], s[..., 3] + angle], dim=-1)
        valid = getattr(batch, f"{key}_valid")[..., None]
        out[key] = torch.where(valid, moved, 0.0)
    return dataclasses.replace(batch, **out)


def _pad_agents(value: torch.Tensor, axes: int, extra: int) -> torch.Tensor:
    """``extra`` zero (False) slots appended to dims ``1 .. axes`` (the agent axes)."""
    pad = []
    for dim in reversed(range(value.ndim)):
        pad += [0, extra if 1 <= dim <= axes else 0]
    return F.pad(value, pad)


def test_history_features_are_in_each_agents_own_frame():
    batch = synthetic_batch(1, 3, seed=0, dtype=torch.float64)
    features = history_features(batch)
    valid = batch.history_valid
    current = features[:, :, -1]
    torch.testing.assert_close(current[..., :2], torch.zeros_like(current[..., :2]))
    torch.testing.assert_close(current[..., 2], torch.ones_like(current[..., 2]))  # cos 0
    # Nearly straight driving: the past lies behind (x < 0), close to the agent's own axis.
    past = features[:, :, 0]
    assert bool((past[..., 0][valid[:, :, 0]] < -5).all())
    assert bool((past[..., 1][valid[:, :, 0]].abs() < 5).all())
    assert not features[~valid].any(), "unobserved steps are zero"


def test_context_is_invariant_to_the_scene_frame(make_model):
    model = make_model(dtype=torch.float64)
    batch = synthetic_batch(2, 5, seed=1, dtype=torch.float64)
    moved = _rigid(batch, angle=0.7, shift=(12.0, -30.0))
    scene, scene_moved = model.encode(batch), model.encode(moved)
    torch.testing.assert_close(scene_moved.context, scene.context)


def test_padded_slots_do_not_change_the_context_of_real_agents(make_model):
    model = make_model(dtype=torch.float64)
    batch = synthetic_batch(2, 4, seed=2, dtype=torch.float64)
    padded = dataclasses.replace(
        batch,
        **{
            key: _pad_agents(value, 2 if key.startswith("pair") else 1, 2)
            for key, value in batch.tensors()
        },
    )
    scene, scene_padded = model.encode(batch), model.encode(padded)
    torch.testing.assert_close(scene_padded.context[:, :4], scene.context)
    assert not scene_padded.context[:, 4:].any()


def test_fully_padded_scene_gives_finite_outputs_and_gradients(make_model):
    model = make_model()
    batch = synthetic_batch(2, 4, seed=3)
    for key in ("history_valid", "agent_mask", "pair_mask", "future_valid", "actions_valid"):
        getattr(batch, key)[1] = False
    z = torch.randn(2, 4, 52, 2)
    u = model(batch, z, torch.tensor([0.1, 0.2]), torch.tensor([0.5, 0.9]))
    assert torch.isfinite(u).all() and not u[1].any()
    u.square().sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_bad_batches_are_rejected_with_the_field_named(make_model):
    model = make_model()
    batch = synthetic_batch(1, 3)
    with pytest.raises(TypeError, match="WindowBatch"):
        model.encode(dict(batch.tensors()))
    wrong = dataclasses.replace(batch, map_crops=batch.map_crops[..., :32, :32])
    with pytest.raises(ValueError, match="map_crops"):
        model.encode(wrong)
    with pytest.raises(ValueError, match="pair_features"):
        dataclasses.replace(batch, pair_features=batch.pair_features[:, :2])
