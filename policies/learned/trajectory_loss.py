"""The trajectory-space loss every generator kind trains with (MeanFlow and diffusion).

A reconstruction ``a_hat`` of the normalised action plan is de-normalised, rolled out
through ``riskflow_env.dynamics.rollout`` from every agent's current state and compared
with the reference future positions (optionally headings), plus the optional collision
and off-road penalties of :mod:`policies.learned.plan_penalties` (RiskFlow paper,
trajectory-space reconstruction; docs/explanation/method.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from policies.dataclass_cli import from_fields
from policies.learned.data import Normalizer
from policies.learned.distributed import masked_mean
from policies.learned.encoder import SceneContext
from policies.learned.plan_penalties import jerk_penalty, offroad_penalty, overlap_penalty
from policies.learned.window_types import WindowBatch
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout, wrap_angle
from riskflow_env.metrics.displacement import masked_displacement


@dataclass(frozen=True)
class LossWeights:
    """Weights of the training loss's terms besides ``position_mse`` (0: the term is left
    out); every generator kind's objective takes one (``riskflow-train``'s
    ``--heading-weight``, ``--action-weight``, ``--collision-weight``,
    ``--offroad-weight``, ``--jerk-weight``).

    Attributes:
        heading: [m^2/rad^2] of ``heading_mse``.
        action: of ``action_mse``, the normalised action error that the objectives add
            (:func:`trajectory_loss` leaves it to them).
        collision: of ``overlap`` (squared penetration depth of decoded box pairs
            [m^2]; from ``length``, ``width``).
        offroad: of ``offroad`` (squared excess of the planned centres' SDF [m^2], from
            ``map_crops``).
        jerk: [m s^3] of ``jerk`` (mean absolute longitudinal jerk of the de-normalised
            plan [m/s^3], every step of every agent in the scene).
    """

    heading: float = 0.0
    action: float = 0.0
    collision: float = 0.0
    offroad: float = 0.0
    jerk: float = 0.0

    @classmethod
    def from_options(cls, options: Any) -> LossWeights:
        """The weights that ``riskflow-train``'s options give (``heading_weight`` for
        ``heading``, and so on)."""
        return from_fields(cls, options, suffix="_weight")


POSITION_ONLY = LossWeights()  # the position error alone


def target_actions(batch: WindowBatch, normalizer: Normalizer) -> Tensor:
    """``a*``: normalised ``batch.actions``, 0 (the mean action) where not valid."""
    valid = batch.actions_valid.bool()[..., None]
    return torch.where(valid, normalizer.normalize(batch.actions), 0.0)


def trajectory_loss(
    a_hat: Tensor,
    batch: WindowBatch,
    scene: SceneContext,
    normalizer: Normalizer,
    weights: LossWeights = POSITION_ONLY,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Masked squared error of the rolled-out reconstruction to the reference future,
    plus the optional realism penalties of :mod:`policies.learned.plan_penalties`.

    Args:
        a_hat: ``(B, A, T, 2)`` normalised reconstructed actions.
        batch: windows with the future fields: ``future (B, A, T, 4)``, ``future_valid
            (B, A, T)`` (scene frame).
        scene: the encoder output (current states and agent mask).
        normalizer: action normalisation.
        weights: ``heading``, ``collision``, ``offroad``, ``jerk`` (``action`` is not
            used here).
        dynamics: time step and bounds of the rollout.

    Returns:
        ``loss = position_mse + heading * heading_mse + collision * overlap + offroad *
        offroad + jerk * jerk`` (weights as ``weights``'s; means over valid agent
        steps, per step: ``|p_hat - p|^2`` [m^2]) and detached metrics ``position_mse``,
        ``heading_mse`` [rad^2], ``ade`` [m] (mean over valid agent-steps), ``fde`` [m]
        (mean over agents of the error at their last valid step:
        :func:`riskflow_env.metrics.displacement.masked_displacement`), and ``overlap`` /
        ``offroad`` / ``jerk`` when their weight is not 0.
    """
    actions = normalizer.denormalize(a_hat)
    trajectory = rollout(scene.state, actions, dynamics)  # (B, A, T, 4)
    future = batch.future
    mask = batch.future_valid.bool() & scene.agent_mask[..., None]
    weight = mask.to(a_hat.dtype)
    count = weight.sum()
    squared = ((trajectory[..., :2] - future[..., :2]) ** 2).sum(dim=-1)  # (B, A, T) [m^2]
    heading = wrap_angle(trajectory[..., 3] - future[..., 3]) ** 2
    position_mse = masked_mean((squared * weight).sum(), count)
    heading_mse = masked_mean((heading * weight).sum(), count)
    loss = position_mse + weights.heading * heading_mse
    penalties = {}
    if weights.collision:
        penalties["overlap"] = overlap_penalty(trajectory, batch, mask)
        loss = loss + weights.collision * penalties["overlap"]
    if weights.offroad:
        penalties["offroad"] = offroad_penalty(trajectory, batch, scene.state, mask)
        loss = loss + weights.offroad * penalties["offroad"]
    if weights.jerk:
        planned = scene.agent_mask[..., None].expand(actions.shape[:-1])
        penalties["jerk"] = jerk_penalty(actions, planned, dynamics.dt)
        loss = loss + weights.jerk * penalties["jerk"]
    with torch.no_grad():
        distance = squared.detach().sqrt()
        # FDE per agent as the metrics define it; "ade" here pools the agent-steps.
        _, final, has_last = masked_displacement(distance, mask)  # (B, A)
        metrics = {
            "position_mse": position_mse.detach(),
            "heading_mse": heading_mse.detach(),
            "ade": masked_mean((distance * weight).sum(), count),
            "fde": masked_mean((final * has_last).sum(), has_last.sum()),
        } | {name: value.detach() for name, value in penalties.items()}
    return loss, metrics


def action_mse(x: Tensor, target: Tensor, batch: WindowBatch, scene: SceneContext) -> Tensor:
    """Mean of ``|x - target|^2`` (summed over the action channels) over the valid actions
    of the scene's agents: the objectives' action-space error.

    Args:
        x: ``(B, A, T, 2)`` normalised actions (or noise), e.g. a reconstruction ``a_hat``.
        target: like ``x``, e.g. ``a*`` (:func:`target_actions`).
        batch: windows with ``actions_valid (B, A, T)``.
        scene: the encoder output (its ``agent_mask (B, A)``).

    Returns:
        A scalar; 0 when nothing is valid.
    """
    weight = (batch.actions_valid.bool() & scene.agent_mask[..., None]).to(x.dtype)
    return masked_mean((((x - target) ** 2).sum(dim=-1) * weight).sum(), weight.sum())
