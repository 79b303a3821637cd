"""Overlap of planned boxes: the score and gradient the avoidance steps and the guidance's
separation term share, and that term, ``L_sep``.

Over the first ``horizon`` steps of each plan (the plans are re-drawn every 0.5 s, so the
near future matters most), the **overlap** of a set of plans is ``sum relu(-separation)^2``
[m^2] over every pair of present agents and step
(``riskflow_env.geometry.separation``: the SAT penetration depth, the simulator's own
collision test), over pairs that do not already overlap now.

``L_sep`` (:class:`Separation`, :func:`separation_term`) is the third term of the guidance
objective every guided adversary shares (:class:`~policies.learned.guidance_losses.
ObjectiveConfig`, ``lambda_sep``): the overlap of every pair of guided boxes of a scene
over the guidance horizon, so that the guided vehicles do not converge on each other, and
of every guided box with a **bystander** of its scene (a present vehicle that is neither
the ego nor guided nor a target: with target ``"ego"``, the vehicles that keep their
unguided plans), whose plan is held fixed, so that an attacker aimed at the ego does not
strike a third vehicle on its way. Not in the RiskFlow paper's objective
(``lambda_sep = 0`` drops it): without it several guided vehicles converge on one target
as a swarm.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from policies.learned.guidance_losses import ObjectiveConfig
from riskflow_env.dynamics import YAW, X, Y
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
    b, m, i, j = touching_pairs(trajectories, length, width, pairs)
    depth = torch.relu(-separation(*pair_boxes(trajectories, length, width, b, m, i, j)))  # (P, T)
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
    b, m, i, j = touching_pairs(trajectories, length, width, pairs, slack)
    gradient = torch.zeros_like(trajectories)
    num_scenes, num_samples, num_agents = trajectories.shape[:3]
    closest = trajectories.new_full((num_scenes * num_samples,), float("inf"))
    if b.numel() == 0:
        return gradient, closest.reshape(num_scenes, num_samples)
    gap, d_xy, d_yaw_i, d_yaw_j = separation_gradient(
        *pair_boxes(trajectories, length, width, b, m, i, j)
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


def pair_separation(states: Tensor, length: Tensor, width: Tensor) -> Tensor:
    """Signed SAT separation [m] of every ordered pair of boxes at every step.

    Args:
        states: ``(..., A, T, 4)`` states (x, y, v, psi).
        length, width: ``(..., A)`` [m], broadcastable against ``states[..., 0, 0]``'s
            leading axes.

    Returns:
        ``(..., A, A, T)``: ``[..., i, j, t]`` of boxes i and j at step t (negative:
        penetration depth).
    """
    xy, yaw = states[..., [X, Y]], states[..., YAW]
    length, width = length[..., None], width[..., None]  # (..., A, 1): every step
    return separation(
        xy[..., :, None, :, :], yaw[..., :, None, :], length[..., :, None, :],
        width[..., :, None, :], xy[..., None, :, :, :], yaw[..., None, :, :],
        length[..., None, :, :], width[..., None, :, :],
    )  # fmt: skip


class Separation:
    """The gradient of ``L_sep`` (module docstring) with respect to the guided
    rows' trajectories: the summed squared penetration depth of every pair of guided boxes
    of one scene, and of every guided box with every bystander of its scene (fixed plans),
    over the first ``horizon`` steps, in closed form (:func:`overlap_gradient`, the
    avoidance steps' objective). Shared by output-space guidance, STRIVE-style's latent
    optimisation and the diffusion baselines' guidance.

    Args:
        length, width: (C,) [m] of the guided rows.
        scene_of_row: (C,) the scene of each row (pairs are taken within a scene).
        horizon: ``T_g`` steps; None: the whole plan.
        bystanders: None, or ``(trajectories, length, width, scene)``: (O, T, 4) fixed
            plans (scene frame), (O,) [m], (O,) [m] and (O,) the scene of each.
    """

    def __init__(
        self,
        length: Tensor,
        width: Tensor,
        scene_of_row: Tensor,
        horizon: int | None,
        bystanders: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
    ) -> None:
        self.fixed = None
        if bystanders is not None:
            fixed, fixed_length, fixed_width, scene_of_fixed = bystanders
            self.fixed = fixed[:, :horizon].detach()
            length, width = torch.cat([length, fixed_length]), torch.cat([width, fixed_width])
            guided = torch.arange(length.shape[0], device=length.device) < scene_of_row.shape[0]
            scene_of_row = torch.cat([scene_of_row, scene_of_fixed])
        pairs = (scene_of_row[:, None] == scene_of_row[None, :]).triu(diagonal=1)
        if self.fixed is not None:
            pairs &= guided[:, None]  # guided with guided or with a bystander (listed last)
        self.boxes = (length[None], width[None], pairs[None])  # one "scene" of all boxes
        self.horizon = horizon

    def gradient(self, trajectories: Tensor) -> Tensor:
        """(C, T, 4) ``d L_sep / d trajectories`` of (C, T, 4) states (zero beyond the
        horizon and in the speed channel)."""
        gradient = torch.zeros_like(trajectories)
        near = trajectories[:, : self.horizon].detach()  # (C, T_g, 4)
        if self.fixed is not None:
            near = torch.cat([near, self.fixed])
        near = near[None, None]  # (1, 1, C [+ O], T_g, 4)
        count = trajectories.shape[0]
        gradient[:, : self.horizon] = overlap_gradient(near, *self.boxes)[0][0, 0, :count]
        return gradient


def separation_term(
    scene: Any,
    rows: Tensor,
    config: ObjectiveConfig,
    scene_of_row: Tensor | None = None,
    bystanders: Tensor | None = None,
    scene_of_bystander: Tensor | None = None,
) -> Separation | None:
    """``L_sep`` of the ``rows`` of ``scene`` (anything with (N,) ``length`` and ``width``
    [m]; ``rows`` (C,) index them), or None when ``config.lambda_sep`` is 0;
    ``scene_of_row`` (C,) the scene of each row (None: one scene), as for
    :func:`~policies.learned.guidance_losses.map_term`. ``bystanders`` (O,) index the
    agents of ``scene`` whose fixed plans (``scene.base_trajectories``, (N, T, 4)) the rows
    keep clear of too, ``scene_of_bystander`` (O,) their scenes (None: one scene); None or
    empty: none (the guided boxes among themselves only)."""
    if not config.lambda_sep:
        return None
    same = torch.zeros_like(rows) if scene_of_row is None else scene_of_row
    fixed = None
    if bystanders is not None and bystanders.numel() > 0:
        if scene_of_bystander is None:
            scene_of_bystander = torch.zeros_like(bystanders)
        if scene_of_bystander.shape != bystanders.shape:
            raise ValueError(
                f"scene_of_bystander must have bystanders' shape {tuple(bystanders.shape)}, "
                f"got {tuple(scene_of_bystander.shape)}"
            )
        fixed = (
            scene.base_trajectories[bystanders],
            scene.length[bystanders],
            scene.width[bystanders],
            scene_of_bystander,
        )
    return Separation(scene.length[rows], scene.width[rows], same, config.resolved_horizon, fixed)


def touching_pairs(
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


def pair_boxes(
    trajectories: Tensor, length: Tensor, width: Tensor, b, m, i, j
) -> tuple[Tensor, ...]:
    """The boxes of pairs ``(b, m, i, j)`` as :func:`~riskflow_env.geometry.separation`
    takes them: ``(P, T, 2)``, ``(P, T)``, ``(P, 1)``, ``(P, 1)`` for i, then for j."""
    xy, yaw = trajectories[..., :2], trajectories[..., 3]

    def box(k: Tensor) -> tuple[Tensor, ...]:
        return xy[b, m, k], yaw[b, m, k], length[b, k, None], width[b, k, None]

    return *box(i), *box(j)


__all__ = [
    "OVERLAP_HORIZON",
    "Separation",
    "overlap_gradient",
    "overlap_scores",
    "pair_boxes",
    "pair_separation",
    "scored_pairs",
    "separation_term",
    "touching_pairs",
]
