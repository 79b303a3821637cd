"""Avoidance steps: a few gradient steps that pull a joint base plan's boxes apart and
keep them on the road, before anything else uses the plan.

The one-step generator draws every agent's plan of a scene from one noise sample, and
the plans of neighbours overlap where the model's interaction is weak (one-shot plans of
the shipped generator overlap in 28% of the evaluation scenes, the log in none:
docs/REALISM.md). Rule guidance of the sampler's output is how CTG (Zhong et al. 2023,
"Guided Conditional Diffusion for Controllable Traffic Simulation", ICRA) keeps its
traffic from colliding and leaving the road; here it is applied to the one-step output
``u`` (normalised action space) of every agent at once, with the same objective as the
best-of-M selection (:mod:`policies.learned.plan_selection`) over its first
``SELECTION_HORIZON`` steps:

    L(u) = sum_pairs relu(-separation)^2 + L_map,   u <- Adam(u, grad L),

the overlap summed over every pair of present agents that is apart now (the SAT
penetration depth, the simulator's own collision test) and ``L_map`` the guidance's map
term of every agent. The variables are the rows of the moving vehicles: the ego's row is
not one (the ego is not driven by the scene policy; the others avoid its predicted
plan), nor are absent rows, nor vehicles at rest (speed <= ``REST_SPEED``): they are
obstacles here, and whether they start is the generator's decision (and the holding
rule's, :mod:`policies.learned.plan_stitching`); as variables, the map term drove parked
cars that the map's raster shows off the road onto it (the real scenes). Autograd through
the differentiable rollout; ``steps = 0`` leaves the plans as they are.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from policies.learned.data import Normalizer
from policies.learned.plan_selection import SELECTION_HORIZON, overlap_scores
from policies.learned.plan_stitching import REST_SPEED
from policies.learned.sampler import decode_plans
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED


def avoid_overlaps(
    eps: Tensor,
    u0: Tensor,
    state: Tensor,
    length: Tensor,
    width: Tensor,
    agent_mask: Tensor,
    map_loss: Callable[[Tensor], Tensor] | None,
    normalizer: Normalizer,
    dynamics: DynamicsConfig,
    *,
    steps: int,
    step_size: float,
    ego: int = 0,
    horizon: int = SELECTION_HORIZON,
) -> tuple[Tensor, Tensor, Tensor]:
    """Avoidance steps on the base plans of B scenes (module docstring).

    Args:
        eps: ``(B, A, T, 2)`` noise; ``u0`` the same shape, the base residual.
        state: ``(B, A, 4)`` current states (scene frame).
        length, width: ``(B, A)`` [m]; ``agent_mask`` ``(B, A)`` bool, present agents.
        map_loss: ``(B * A, T_s, 4) -> scalar`` the map term of every row (differentiable),
            or None (no map term).
        normalizer, dynamics: the plans' decoding (:func:`~policies.learned.sampler.decode_plans`).
        steps: Adam steps (0: ``u0`` unchanged); ``step_size`` its learning rate
            [normalised action units].
        ego: the ego's slot (not a variable; nor are vehicles at rest).
        horizon: plan steps in the objective.

    Returns:
        ``(u, actions, trajectories)``: ``(B, A, T, 2)``, ``(B, A, T, 2)``, ``(B, A, T, 4)``.
    """
    variable = agent_mask & (state[..., SPEED] > REST_SPEED)
    variable[:, ego] = False
    mask = variable[..., None, None].to(u0.dtype)
    u = u0.detach().clone()
    if steps > 0 and bool(variable.any()):
        delta = torch.zeros_like(u, requires_grad=True)
        optimizer = torch.optim.Adam([delta], lr=step_size)
        with torch.enable_grad():
            for _ in range(steps):
                _, trajectories = decode_plans(
                    eps + u + delta * mask, state, agent_mask, normalizer, dynamics
                )
                scored = trajectories[..., :horizon, :]
                loss = overlap_scores(scored[:, None], length, width, agent_mask, state).sum()
                if map_loss is not None:
                    loss = loss + map_loss(scored.flatten(0, 1))
                optimizer.zero_grad(set_to_none=False)
                loss.backward()
                optimizer.step()
        u = u + delta.detach() * mask
    actions, trajectories = decode_plans(eps + u, state, agent_mask, normalizer, dynamics)
    return u, actions, trajectories


__all__ = ["avoid_overlaps"]
