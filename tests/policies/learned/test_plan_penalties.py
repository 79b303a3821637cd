"""Realism penalties on decoded plans: closed-form cases and gradients."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch

from policies.learned.plan_penalties import jerk_penalty, offroad_penalty, overlap_penalty


def _states(xy, yaw=0.0):
    xy = torch.tensor(xy, dtype=torch.float64)  # (A, T, 2)
    heading = torch.full(xy.shape[:-1], yaw, dtype=torch.float64)
    speed = torch.zeros_like(heading)
    return torch.stack([xy[..., 0], xy[..., 1], speed, heading], dim=-1)[None]  # (1, A, T, 4)


def test_overlap_penalty_is_the_squared_penetration_depth():
    # Two 4 x 2 m boxes side by side, heading +x: centres 1.5 m apart laterally -> 0.5 m deep.
    planned = _states([[[0.0, 0.0]], [[0.0, 1.5]]]).requires_grad_(True)
    reference = _states([[[0.0, 0.0]], [[0.0, 3.0]]])  # apart in the log
    batch = SimpleNamespace(
        future=reference,
        length=torch.full((1, 2), 4.0, dtype=torch.float64),
        width=torch.full((1, 2), 2.0, dtype=torch.float64),
    )  # the fields of a WindowBatch the penalty reads
    valid = torch.ones(1, 2, 1, dtype=torch.bool)
    penalty = overlap_penalty(planned, batch, valid)
    assert math.isclose(float(penalty.detach()), 0.5**2 / 2)  # one pair, two agent-steps
    penalty.backward()  # it pushes the boxes apart: agent 1 to +y, agent 0 to -y
    assert planned.grad[0, 1, 0, 1] < 0 < planned.grad[0, 0, 0, 1]
    # Pairs that overlap in the reference are not penalised; nor are invalid agents.
    batch.future = planned.detach()
    assert float(overlap_penalty(planned, batch, valid)) == 0.0
    batch.future = reference
    assert float(overlap_penalty(planned, batch, valid & torch.tensor([True, False])[:, None])) == 0


def test_offroad_penalty_reads_the_agents_own_crop():
    size = 9  # 1 m/px, agent at the centre pixel (4, 4); road where forward <= 1 m
    forward = torch.arange(size, dtype=torch.float64) - 4.0
    sdf = (forward - 1.0).expand(size, size)  # columns run forward: sdf = forward - 1
    crops = torch.stack([torch.zeros(size, size, dtype=torch.float64), sdf])[None, None]
    start = torch.tensor([[[10.0, 5.0, 0.0, math.pi / 2]]], dtype=torch.float64)  # facing +y
    planned = _states([[[10.0, 8.0], [10.0, 20.0]]], yaw=math.pi / 2)  # 3 m ahead; off crop
    reference = _states([[[10.0, 5.0], [10.0, 5.0]]], yaw=math.pi / 2)
    batch = SimpleNamespace(future=reference, width=torch.full((1, 1), 2.0), map_crops=crops)
    valid = torch.ones(1, 1, 2, dtype=torch.bool)
    penalty = offroad_penalty(planned, batch, start, valid)
    # sdf 2 m + half width 1 m - allowance relu(-1 + 1) = 0 -> 3^2 over 2 agent-steps.
    assert math.isclose(float(penalty), 9.0 / 2, rel_tol=1e-9)


def test_jerk_penalty_is_the_mean_absolute_jerk_of_the_counted_steps():
    # Accelerations 0, 1, 1, -1 m/s^2 at dt = 0.5 s: jerks 2, 0, -4 m/s^3 -> mean |j| 2.
    accel = torch.tensor([[[0.0, 1.0, 1.0, -1.0]]], dtype=torch.float64)
    actions = torch.stack([accel, torch.full_like(accel, 0.3)], dim=-1).requires_grad_(True)
    valid = torch.ones(1, 1, 4, dtype=torch.bool)
    penalty = jerk_penalty(actions, valid, dt=0.5)
    assert math.isclose(float(penalty), 2.0)
    penalty.backward()  # L1: every change pulled toward 0 with the same force; yaw rate free
    grad = actions.grad[0, 0]
    assert torch.equal(grad[:, 1], torch.zeros(4, dtype=torch.float64))
    # d/da of |a1 - a0| / dt / 3 etc.: the ends move toward their neighbours, |grad| 2/3
    expected = torch.tensor([-2.0, 2.0, 2.0, -2.0], dtype=torch.float64) / 3
    assert torch.allclose(grad[:, 0], expected)
    # A sample needs both of its steps: dropping the last step leaves jerks 2 and 0.
    valid[..., 3] = False
    assert math.isclose(float(jerk_penalty(actions, valid, dt=0.5)), 1.0)
    assert float(jerk_penalty(actions, torch.zeros_like(valid), dt=0.5)) == 0.0
