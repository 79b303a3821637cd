"""Best of M joint plans: a rule-based score that keeps the plan set that collides least.

The one-step generator draws a *joint* plan of every agent of a scene from one noise
sample. Drawing M samples and keeping, per scene, the one with the lowest score is the
selection step of BITS's prediction-and-planning module (Xu et al. 2023, "BITS:
Bi-level Imitation for Traffic Simulation", ICRA: sample several candidates, score them
with rules such as collision and off-road, keep the best), here applied to whole joint
plans, so the kept plans stay samples of the generator (no output is edited) and the
agents' plans stay mutually consistent.

The score of a joint plan, over its first ``horizon`` steps (the plans are re-drawn every
0.5 s, so the near future matters most):

* **overlap**: ``sum relu(-separation)^2`` [m^2] over every pair of present agents and
  step (``riskflow_env.geometry.separation``: the SAT penetration depth, the simulator's
  own collision test), over pairs that do not already overlap now;
* **off-road**: the guidance's map term ``L_map`` of every present agent
  (:class:`~policies.learned.guidance_losses.MapTerm`: decayed squared off-road depth of
  the footprint samples [m^2]).

Both are in m^2 and are added.

:func:`select_attack_plans` is the adversary's counterpart, per guided vehicle: among M
samples of its plan it keeps the one the guidance objective scores best (nearest its
targets, on the road), so that guidance starts from a sample of the generator that already
heads for an interaction instead of bending a plan that does not.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from policies.learned.adversarial_term import adversarial_rows
from policies.learned.guidance_losses import ObjectiveConfig
from policies.learned.plan_penalties import pair_separation
from riskflow_env.geometry import separation, separation_gradient

SELECTION_HORIZON = 30
"""steps of each plan the score looks at (3 s of the 5.2 s plan)"""


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


def select_joint_plans(
    trajectories: Tensor,
    length: Tensor,
    width: Tensor,
    agent_mask: Tensor,
    now: Tensor,
    map_rows: Callable[[Tensor], Tensor] | None,
    horizon: int = SELECTION_HORIZON,
) -> tuple[Tensor, Tensor]:
    """The index of the best of M joint plans of each scene (module docstring).

    Args:
        trajectories: ``(B, M, A, T, 4)``.
        length, width, agent_mask, now: as :func:`overlap_scores`.
        map_rows: ``(B * A, T_s, 4) -> (B * A,)`` the map term of each agent's plan
            (rows of absent agents are ignored), or None (no map term).
        horizon: steps scored.

    Returns:
        ``(B,)`` int64 indices into M, and the ``(B, M)`` scores.
    """
    scored = trajectories[..., :horizon, :]
    scores = overlap_scores(scored, length, width, agent_mask, now)
    if map_rows is not None:
        num_scenes, num_samples, num_agents = scored.shape[:3]
        flat = scored.transpose(0, 1).reshape(
            num_samples, num_scenes * num_agents, *scored.shape[3:]
        )
        per_row = torch.stack([map_rows(sample) for sample in flat])  # (M, B * A)
        per_row = per_row.reshape(num_samples, num_scenes, num_agents) * agent_mask
        scores = scores + per_row.sum(dim=-1).transpose(0, 1)
    return scores.argmin(dim=1), scores


def select_attack_plans(
    trajectories: Tensor,
    target_xy: Tensor,
    controllable: Tensor,
    targets: Tensor,
    objective: ObjectiveConfig,
    map_rows: Callable[[Tensor], Tensor] | None,
    horizon: int = SELECTION_HORIZON,
) -> Tensor:
    """Per controllable vehicle, the index of the best of its M sampled plans by
    ``lambda_adv * L_adv + lambda_map * L_map`` (module docstring): the guidance objective's
    two terms, ``L_map`` over the first ``horizon`` steps, against the targets' plans as
    given (``L_sep`` is left to guidance).

    Args:
        trajectories: ``(B, M, A, T, 4)`` the M samples of every agent's plan.
        target_xy: ``(B, A, T, 2)`` [m] the plans the targets follow (held fixed, as
            guidance holds them).
        controllable: ``(B, A)`` bool, the vehicles to choose for (``A_c``).
        targets: ``(B, A)`` bool, the agents ``L_adv`` pulls toward
            (:func:`~policies.learned.guidance_losses.target_rows`).
        objective: the weights, ``L_adv``'s horizon and temperature.
        map_rows: ``(M * C, T_s, 4) -> (M * C,)`` the map term of the C controllable rows,
            sample-major (sample 0's C rows in ``controllable.nonzero()`` order, then
            sample 1's, ...: the rows of a map term built for ``rows.repeat(M)``), or None
            (no map term).
        horizon: steps of the map term.

    Returns:
        ``(B, A)`` int64 indices into M; 0 outside ``controllable``.
    """
    num_scenes, num_samples = trajectories.shape[:2]
    pick = torch.zeros(controllable.shape, dtype=torch.long, device=trajectories.device)
    scene, agent = torch.nonzero(controllable, as_tuple=True)
    if scene.numel() == 0:
        return pick
    rows = trajectories[scene, :, agent].transpose(0, 1).flatten(0, 1)  # (M * C, T, 4)
    per_row_targets = target_xy[scene].repeat(num_samples, 1, 1, 1)  # (M * C, A, T, 2)
    valid = targets[scene].repeat(num_samples, 1)
    adv, _ = adversarial_rows(
        rows[..., :2], per_row_targets, objective.horizon, valid, False, objective.adv_temperature
    )
    score = objective.lambda_adv * adv
    if map_rows is not None and objective.lambda_map:
        score = score + objective.lambda_map * map_rows(rows[:, :horizon])
    pick[scene, agent] = score.reshape(num_samples, -1).argmin(dim=0)
    return pick


__all__ = [
    "SELECTION_HORIZON",
    "overlap_gradient",
    "overlap_scores",
    "scored_pairs",
    "select_attack_plans",
    "select_joint_plans",
]
