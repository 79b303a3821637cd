"""Trajectory-space realism penalties on decoded plans: box overlap, leaving the road, jerk.

The trajectory-space loss pulls each agent's plan toward its own logged future; nothing
in it says that two plans must not overlap or that a plan must stay on the road, and
one-shot joint plans of the shipped generator overlapped in 57% of scenes (the log: 0%).
The first two terms say it, through pieces the simulator already has; the third asks for
the data's smoothness:

* :func:`overlap_penalty`: ``relu(-separation)^2`` [m^2] of every pair of decoded boxes at
  every step (``riskflow_env.geometry.separation``: the SAT penetration depth, the
  simulator's own collision test, differentiable almost everywhere), over pairs that do
  not overlap in the reference at that step;
* :func:`offroad_penalty`: ``relu(sdf + w / 2 - allowance)^2`` [m^2] at each planned
  centre, read bilinearly from the agent's own map crop (``map_crops`` channel 1: the
  SDF [m], negative on the road; ``docs/how-to/windows.md``), where ``w / 2`` asks for the
  whole width on the road and ``allowance = relu(sdf_ref + w / 2)`` forgives what the
  reference itself does. Steps that leave the crop (48 m at 1 m/px: about the first
  2 s at highway speed) get no term;
* :func:`jerk_penalty`: the mean ``|j|`` [m/s^3] of the plan's longitudinal jerk ``j_t =
  (a_{t+1} - a_t) / dt``. Half the logged steps have ``|j| < 0.1`` while the one-step
  plans of the shipped generator carry step-to-step noise on every step (median 1.2
  m/s^3), which is most of KDD's jerk term. An L1 term (total
  variation of the acceleration, Rudin, Osher & Fatemi 1992) pulls small changes to zero
  and leaves the few large ones the data has, where a squared one would shrink them all.

All three are means over the agent-steps that count in the batch, so their weights
compare with the position MSE [m^2] of the trajectory loss.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from policies.learned.distributed import masked_mean
from policies.learned.plan_overlap import pair_separation
from policies.learned.window_types import WindowBatch
from riskflow_env.dynamics import ACCEL, YAW, X, Y
from riskflow_env.geometry import to_frame

SDF_CHANNEL = 1  # policies.learned.windows.CROP_LAYERS = ("drivable", "sdf")


def overlap_penalty(trajectory: Tensor, batch: WindowBatch, valid: Tensor) -> Tensor:
    """Mean squared penetration depth of decoded box pairs [m^2].

    Args:
        trajectory: ``(B, A, T, 4)`` decoded states, scene frame.
        batch: ``future (B, A, T, 4)``, ``length``, ``width`` ``(B, A)`` [m].
        valid: ``(B, A, T)`` bool, agent-steps that count.

    Returns:
        Scalar: the sum over unordered pairs and steps of ``relu(-separation)^2``
        divided by the number of valid agent-steps.
    """
    length, width = batch.length, batch.width
    num_agents = valid.shape[1]
    upper = torch.ones(num_agents, num_agents, dtype=torch.bool, device=valid.device).triu(1)
    pairs = valid[:, :, None] & valid[:, None] & upper[None, :, :, None]
    with torch.no_grad():
        apart = pair_separation(batch.future, length, width) > 0.0
        pairs = pairs & apart  # the reference does not overlap
    depth = torch.relu(-pair_separation(trajectory, length, width)) * pairs
    return masked_mean((depth**2).sum(), valid.sum())


def offroad_penalty(
    trajectory: Tensor,
    batch: WindowBatch,
    start: Tensor,
    valid: Tensor,
    crop_resolution: float = 1.0,
) -> Tensor:
    """Mean squared excess of the planned centres' SDF over the reference's [m^2].

    Args:
        trajectory: ``(B, A, T, 4)`` decoded states, scene frame.
        batch: ``future``, ``width`` and ``map_crops (B, A, C, S, S)`` (agent-centred,
            heading-aligned at the current step; columns forward, rows left).
        start: ``(B, A, 4)`` current states, scene frame (the crops' centres and axes).
        valid: ``(B, A, T)`` bool, agent-steps that count.
        crop_resolution: crop pixel size [m/px].

    Returns:
        Scalar, see the module docstring.
    """
    crops = batch.map_crops[:, :, SDF_CHANNEL]  # (B, A, S, S)
    size = crops.shape[-1]
    cos, sin = torch.cos(start[..., YAW])[..., None], torch.sin(start[..., YAW])[..., None]

    def sdf_at(states: Tensor) -> tuple[Tensor, Tensor]:  # (B, A, T) sdf [m], inside crop
        dx = states[..., X] - start[..., X, None]
        dy = states[..., Y] - start[..., Y, None]
        # crop_points: pixel (r, c) at forward (c - (S-1)/2) * res, left (r - (S-1)/2) * res
        forward, left = to_frame(dx, dy, cos, sin)
        forward, left = forward / crop_resolution, left / crop_resolution
        half = (size - 1) / 2.0
        grid = torch.stack([forward / half, left / half], dim=-1)  # (x -> columns, y -> rows)
        inside = (grid.abs() <= 1.0).all(dim=-1)
        b, a, t = forward.shape
        sampled = F.grid_sample(
            crops.reshape(b * a, 1, size, size),
            grid.reshape(b * a, t, 1, 2),
            mode="bilinear",
            padding_mode="border",
            align_corners=True,
        )
        return sampled.reshape(b, a, t), inside

    half_width = 0.5 * batch.width[..., None]
    with torch.no_grad():
        reference, _ = sdf_at(batch.future)
        allowance = torch.relu(reference + half_width)
    planned, inside = sdf_at(trajectory)
    excess = torch.relu(planned + half_width - allowance) * (valid & inside)
    return masked_mean((excess**2).sum(), valid.sum())


def jerk_penalty(actions: Tensor, valid: Tensor, dt: float) -> Tensor:
    """Mean absolute longitudinal jerk of plans [m/s^3] (module docstring).

    Args:
        actions: ``(B, A, T, 2)`` de-normalised plans (acceleration [m/s^2], yaw rate).
        valid: ``(B, A, T)`` bool, plan steps that count; a jerk sample needs both ends.
        dt: time step [s].

    Returns:
        Scalar: ``sum |a_{t+1} - a_t| / dt`` over samples whose two steps count, divided
        by their number.
    """
    jerk = (actions[..., 1:, ACCEL] - actions[..., :-1, ACCEL]).abs() / dt
    both = valid[..., 1:] & valid[..., :-1]
    return masked_mean((jerk * both).sum(), both.sum())
