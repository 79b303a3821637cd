"""Overlap of planned boxes: the score and gradient the avoidance steps and the guidance's
separation term share.

Over the first ``horizon`` steps of each plan (the plans are re-drawn every 0.5 s, so the
near future matters most), the **overlap** of a set of plans is ``sum relu(-separation)^2``
[m^2] over every pair of present agents and step
(``riskflow_env.geometry.separation``: the SAT penetration depth, the simulator's own
collision test), over pairs that do not already overlap now.
"""

from __future__ import annotations

import torch
from torch import Tensor

from policies.learned.plan_penalties import pair_separation
from riskflow_env.geometry import separation, separation_gradient

OVERLAP_HORIZON = 30
"""steps of each plan the overlap score looks at (3 s of the 5.2 s plan)"""


def scored_pairs(length: Tensor, width: Tensor, agent_mask: Tensor, now: Tensor) -> Tensor:
    """``(B, A, A)`` bool: the pairs ``i < j`` of present agents that are apart now, those
    that :func:`overlap_scores` counts."""
    num_agents = agent_mask.shape[-1]
    upper = torch.ones(num_agents, num_agents, dtype=torch.bool, device=agent_mask.device).triu(1)
    pairs = agent_mask[:, :, None] & agent_mask[:, None, :] & upper  # (B, A, A)
    return pairs & (pair_separation(now[:, :, None], length, width)[..., 0] > 0.0)


def overlap_scores(
    trajectories: Tensor,
    length: Tensor,
    width: Tensor,
    agent_mask: Tensor,
    now: Tensor,
    pairs: Tensor | None = None,
) -> Tensor:
    """Summed squared penetration depth [m^2] of each joint plan.

    Only pairs that can touch are tested: two boxes that overlap have centres closer than
    the sum of their half-diagonals, so pairs whose centres are farther apart at every
    step are skipped (no autograd graph is built for them); the value and its gradient
    are those of testing every pair, to float rounding.

    Args:
        trajectories: ``(B, M, A, T, 4)`` M joint plans of B scenes (scene frame).
        length, width: ``(B, A)`` [m].
        agent_mask: ``(B, A)`` bool, present agents.
        now: ``(B, A, 4)`` current states (pairs overlapping now are not counted).
        pairs: ``(B, A, A)`` bool, :func:`scored_pairs` of ``agent_mask`` and ``now``,
            or a subset of them (computed when None; callers that score many plans of
            the same scenes compute it once).

    Returns:
        ``(B, M)``.
    """
    num_scenes, num_samples = trajectories.shape[:2]
    if pairs is None:
        pairs = scored_pairs(length, width, agent_mask, now)
    b, m, i, j = _touching(trajectories, length, width, pairs)
    depth = torch.relu(-separation(*_boxes(trajectories, length, width, b, m, i, j)))  # (P, T)
    per_pair = (depth**2).sum(dim=-1)
    scores = trajectories.new_zeros(num_scenes * num_samples)
    return scores.index_add(0, b * num_samples + m, per_pair).reshape(num_scenes, num_samples)


def overlap_gradient(
    trajectories: Tensor, length: Tensor, width: Tensor, pairs: Tensor, slack: float = 0.0
) -> tuple[Tensor, Tensor]:
    """The gradient of :func:`overlap_scores` (summed) with respect to ``trajectories``,
    in closed form (:func:`riskflow_env.geometry.separation_gradient`), with no autograd
    graph: the avoidance steps' (:mod:`policies.learned.plan_avoidance`). The same as
    autograd's to float rounding wherever no two SAT gaps tie.

    Args:
        trajectories: ``(B, M, A, T, 4)``; ``length``, ``width`` ``(B, A)``; ``pairs``
            ``(B, A, A)`` bool, the pairs scored (as :func:`overlap_scores`).
        slack: [m] pairs whose centres are within the sum of their half-diagonals plus
            this are tested (0 finds every overlap; more, every pair closer than it too).

    Returns:
        ``(gradient, closest)``: ``(B, M, A, T, 4)``, zero in the speed channel and
        wherever no pair overlaps, and ``(B, M)`` the smallest separation [m] of the
        pairs tested in each joint plan (``inf`` where none is).
    """
    b, m, i, j = _touching(trajectories, length, width, pairs, slack)
    gradient = torch.zeros_like(trajectories)
    num_scenes, num_samples, num_agents = trajectories.shape[:3]
    closest = trajectories.new_full((num_scenes * num_samples,), float("inf"))
    if b.numel() == 0:
        return gradient, closest.reshape(num_scenes, num_samples)
    gap, d_xy, d_yaw_i, d_yaw_j = separation_gradient(
        *_boxes(trajectories, length, width, b, m, i, j)
    )
    weight = 2.0 * torch.clamp(gap, max=0.0)  # d relu(-gap)^2 / d gap, (P, T)
    d_xy = weight[..., None] * d_xy
    flat = gradient.flatten(0, 2)  # (B * M * A, T, 4)
    plan = b * num_samples + m
    for rows, sign, d_yaw in (
        (plan * num_agents + i, -1.0, d_yaw_i),
        (plan * num_agents + j, 1.0, d_yaw_j),
    ):
        flat[..., :2].index_add_(0, rows, sign * d_xy)
        flat[..., 3].index_add_(0, rows, weight * d_yaw)
    closest = closest.scatter_reduce(0, plan, gap.amin(dim=-1), reduce="amin")
    return gradient, closest.reshape(num_scenes, num_samples)


def _touching(
    trajectories: Tensor, length: Tensor, width: Tensor, pairs: Tensor, slack: float = 0.0
) -> tuple[Tensor, ...]:
    """``(b, m, i, j)``: the scored pairs of each joint plan whose boxes can touch (their
    centres are closer than the sum of their half-diagonals, plus ``slack`` [m], at some
    step)."""
    xy = trajectories[..., :2]
    b, i, j = torch.nonzero(pairs, as_tuple=True)  # (P,) the pairs scored
    with torch.no_grad():
        reach = 0.5 * torch.hypot(length, width)  # (B, A) half-diagonals
        touch = (reach[b, i] + reach[b, j])[:, None, None] + slack  # (P, 1, 1)
        centres = torch.linalg.vector_norm(xy[b, :, i] - xy[b, :, j], dim=-1)  # (P, M, T)
        pair, m = torch.nonzero((centres <= touch).any(dim=-1), as_tuple=True)
    return b[pair], m, i[pair], j[pair]


def _boxes(trajectories: Tensor, length: Tensor, width: Tensor, b, m, i, j) -> tuple[Tensor, ...]:
    """The boxes of pairs ``(b, m, i, j)`` as :func:`~riskflow_env.geometry.separation`
    takes them: ``(P, T, 2)``, ``(P, T)``, ``(P, 1)``, ``(P, 1)`` for i, then for j."""
    xy, yaw = trajectories[..., :2], trajectories[..., 3]

    def box(k: Tensor) -> tuple[Tensor, ...]:
        return xy[b, m, k], yaw[b, m, k], length[b, k, None], width[b, k, None]

    return *box(i), *box(j)


__all__ = [
    "OVERLAP_HORIZON",
    "overlap_gradient",
    "overlap_scores",
    "scored_pairs",
]
