"""Random but dynamically consistent window batches, for tests and benchmarks.

:func:`synthetic_batch` makes a :class:`~policies.learned.window_types.WindowBatch`
(``docs/how-to/windows.md``, future fields included)
without any data or map: vehicles on a straight three-lane road, driven by smooth
random actions through ``riskflow_env.dynamics.rollout``, so ``rollout(current
state, actions)`` reproduces ``future`` exactly (no bound is reached). Some scenes
have padded agent slots, some agents appear late in the history or leave the
future early. The map crops show the road band (|y| < 6 m) around each agent.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from policies.learned.window_types import PAD_INDEX, WindowBatch
from riskflow_env.dynamics import rollout
from riskflow_env.geometry import to_frame
from riskflow_env.risk import pairwise_features

ROAD_HALF_WIDTH = 6.0  # [m]
SDF_CLIP = 10.0  # [m], as policies.learned.windows.WindowConfig.sdf_clip


def _smooth_noise(shape: tuple[int, ...], steps: int, gen: torch.Generator) -> Tensor:
    """``(*shape, steps)`` sums of three random sinusoids, unit-ish amplitude."""
    time = torch.arange(steps, dtype=torch.float64) * 0.1  # [s]
    freq = 0.05 + 0.4 * torch.rand((*shape, 3, 1), generator=gen, dtype=torch.float64)  # [Hz]
    phase = 2 * math.pi * torch.rand((*shape, 3, 1), generator=gen, dtype=torch.float64)
    amp = torch.rand((*shape, 3, 1), generator=gen, dtype=torch.float64)
    return (amp * torch.sin(2 * math.pi * freq * time + phase)).sum(dim=-2) / 1.5


def _to_frame(states: Tensor, pose: Tensor) -> Tensor:
    """States ``(B, A, T, 4)`` into the frame of ``pose (B, 4)`` (x, y, -, psi)."""
    cos, sin = torch.cos(pose[:, 3]), torch.sin(pose[:, 3])
    cos, sin = cos[:, None, None], sin[:, None, None]
    dx, dy = states[..., 0] - pose[:, None, None, 0], states[..., 1] - pose[:, None, None, 1]
    psi = states[..., 3] - pose[:, None, None, 3]
    return torch.stack([*to_frame(dx, dy, cos, sin), states[..., 2], psi], dim=-1)


def _map_crops(current_world: Tensor, size: int) -> Tensor:
    """``(B, A, 2, S, S)`` drivable share and SDF [m] of the road band, 1 m/px, agent frame."""
    offsets = torch.arange(size, dtype=torch.float64) - (size - 1) / 2  # [m]
    forward, left = offsets[None, :], offsets.flip(0)[:, None]  # columns ahead, rows to the left
    y, psi = current_world[..., 1, None, None], current_world[..., 3, None, None]
    y_world = y + torch.sin(psi) * forward + torch.cos(psi) * left  # (B, A, S, S)
    sdf = (y_world.abs() - ROAD_HALF_WIDTH).clamp(-SDF_CLIP, SDF_CLIP)
    return torch.stack([(sdf < 0).to(torch.float64), sdf], dim=2)


def synthetic_batch(
    batch_size: int,
    num_agents: int,
    *,
    seed: int = 0,
    history_steps: int = 31,
    future_steps: int = 52,
    map_size: int = 48,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> WindowBatch:
    """A collated batch of ``batch_size`` scenes with ``num_agents`` slots each.

    Args:
        batch_size: scenes ``B``.
        num_agents: agent slots ``A`` (slot 0 the ego); every odd scene leaves its last
            ``A // 4`` slots padded.
        seed: seed of the generator; the same seed gives the same batch.
        history_steps: states up to and including the current one.
        future_steps: future states (and actions).
        map_size: map crop side [px] (1 m/px).
        dtype: floating dtype of the result.
        device: device of the result.

    Returns:
        The batch, shapes ``(B, A, ...)``; ``agent_index`` is the slot (-1 where padded).
    """
    gen = torch.Generator().manual_seed(seed)
    shape = (batch_size, num_agents)
    f64 = torch.float64
    steps = history_steps - 1 + future_steps  # actions from the oldest history state
    lane = torch.randint(-1, 2, shape, generator=gen).to(f64) * 4.0  # [m]
    start = torch.stack(
        [
            -40.0 + 120.0 * torch.rand(shape, generator=gen, dtype=f64),
            lane + 0.3 * torch.randn(shape, generator=gen, dtype=f64),
            10.0 + 15.0 * torch.rand(shape, generator=gen, dtype=f64),
            0.03 * torch.randn(shape, generator=gen, dtype=f64),
        ],
        dim=-1,
    )
    start[:, 0, :2] = torch.tensor([0.0, 0.0], dtype=f64)
    accel = 1.2 * _smooth_noise(shape, steps, gen)  # [m/s^2]
    yaw_rate = 0.03 * _smooth_noise(shape, steps, gen)  # [rad/s]
    actions = torch.stack([accel, yaw_rate], dim=-1)  # (B, A, steps, 2)
    states = torch.cat([start[:, :, None], rollout(start, actions)], dim=2)  # (B, A, steps+1, 4)
    current_world = states[:, :, history_steps - 1]
    states = _to_frame(states, current_world[:, 0])

    agent_mask = torch.ones(shape, dtype=torch.bool)
    agent_mask[1::2, num_agents - num_agents // 4 :] = False
    steps_hist = torch.arange(history_steps)
    first = torch.randint(0, history_steps // 2, shape, generator=gen)
    late = (torch.rand(shape, generator=gen) < 0.3) & (torch.arange(num_agents) > 0)
    history_valid = (steps_hist >= torch.where(late, first, 0)[..., None]) & agent_mask[..., None]
    last = torch.randint(future_steps // 2, future_steps, shape, generator=gen)
    early = torch.rand(shape, generator=gen) < 0.2
    end = torch.where(early, last, future_steps)[..., None]
    future_valid = (torch.arange(future_steps) < end) & agent_mask[..., None]

    length = 4.0 + torch.rand(shape, generator=gen, dtype=f64)  # [m]
    width = 1.8 + 0.3 * torch.rand(shape, generator=gen, dtype=f64)  # [m]
    pair_features, pair_mask = pairwise_features(
        states[:, :, history_steps - 1], length, width, agent_mask
    )
    mask = agent_mask.to(f64)
    batch = WindowBatch(
        history=states[:, :, :history_steps] * history_valid[..., None],
        history_valid=history_valid,
        future=states[:, :, history_steps:] * future_valid[..., None],
        future_valid=future_valid,
        actions=actions[:, :, history_steps - 1 :] * future_valid[..., None],
        actions_valid=future_valid.clone(),
        agent_mask=agent_mask,
        agent_index=torch.where(agent_mask, torch.arange(num_agents), PAD_INDEX),
        length=length * mask,
        width=width * mask,
        map_crops=_map_crops(current_world, map_size) * mask[..., None, None, None],
        pair_features=pair_features,
        pair_mask=pair_mask,
    )
    return batch.map(
        lambda v: v.to(device=device, dtype=dtype if v.is_floating_point() else v.dtype)
    )
