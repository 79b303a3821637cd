"""One-step sampling of action plans: ``a = eps + u_theta(eps, 0, 1; C)``.

MeanFlow (Geng et al. 2025) samples with one evaluation of the average velocity over
the whole interval: ``z_1 = z_0 + (1 - 0) u(z_0, 0, 1)``, ``z_0 = eps`` (noise at t = 0,
data at t = 1; docs/explanation/method.md). One forward pass serves every agent of every
scene in the batch (and, with ``num_samples``, every sample).
"""

from __future__ import annotations

import torch
from torch import Tensor

from policies.learned.data import Normalizer
from policies.learned.encoder import SceneContext
from policies.learned.generator import RiskFlowGenerator
from policies.learned.window_types import WindowBatch
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import DEFAULT_CONFIG, clip_actions, rollout


def base_velocity(model: RiskFlowGenerator, eps: Tensor, scene: SceneContext) -> Tensor:
    """``u0 = u_theta(eps, 0, 1; C)``: the one-step residual, normalised (differentiable).

    Output-space guidance (docs/explanation/method.md) starts from it; ``eps + u0`` is the plan.

    Args:
        model: the generator.
        eps: ``(B, A, T, 2)`` noise.
        scene: ``model.encode(batch)``.

    Returns:
        ``(B, A, T, 2)``.
    """
    batch = eps.shape[0]
    zeros = torch.zeros(batch, device=eps.device, dtype=eps.dtype)
    return model.average_velocity(eps, zeros, torch.ones_like(zeros), scene)


def draw_noise(
    scene: SceneContext,
    future_steps: int,
    num_samples: int | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Standard normal ``eps``: ``(B, A, T, 2)``, or ``(B, N, A, T, 2)`` with ``num_samples``."""
    batch, agents = scene.agent_mask.shape
    lead = (batch, agents) if num_samples is None else (batch, num_samples, agents)
    return torch.randn(
        (*lead, future_steps, 2),
        generator=generator,
        device=scene.context.device,
        dtype=scene.context.dtype,
    )


def decode_plans(
    a: Tensor,
    state: Tensor,
    agent_mask: Tensor,
    normalizer: Normalizer,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> tuple[Tensor, Tensor]:
    """Actions ``clip(denorm(a))`` (0 for absent agents) and their rollout: what every
    generator's normalised sample ``a`` becomes (:func:`sample`, guidance, the diffusion
    chains).

    Shapes: ``a (..., A, T, 2)``, ``state (..., A, 4)``, ``agent_mask (..., A)``; returns
    ``(..., A, T, 2)`` [m/s^2, rad/s] and ``(..., A, T, 4)`` states.
    """
    actions = clip_actions(normalizer.denormalize(a), dynamics)
    actions = actions * agent_mask[..., None, None].to(actions.dtype)
    return actions, rollout(state, actions, dynamics)


@torch.no_grad()
def sample(
    model: RiskFlowGenerator,
    scene_or_batch: SceneContext | WindowBatch,
    eps: Tensor | None,
    normalizer: Normalizer,
    *,
    num_samples: int | None = None,
    generator: torch.Generator | None = None,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> tuple[Tensor, Tensor]:
    """Sample action plans and their trajectories in one forward pass.

    Args:
        model: the generator.
        scene_or_batch: a :class:`SceneContext` (``model.encode(batch)``) or a batch
            of windows (``docs/how-to/windows.md``; future fields not needed).
        eps: noise ``(B, A, T, 2)``, or ``(B, N, A, T, 2)`` with ``num_samples = N``;
            None draws it from ``generator``. A fixed ``eps`` gives the same plans.
        normalizer: action normalisation (``denormalize``).
        num_samples: ``N`` plans per scene (e.g. for minADE), batched into one pass;
            None for one plan and no sample axis.
        generator: random source when ``eps`` is None.
        dynamics: time step and bounds of the rollout.

    Returns:
        ``actions``: ``(B, [N,] A, T, 2)`` (accel [m/s^2], yaw rate [rad/s]), clipped
        to the dynamics bounds (exactly what the rollout applies) and 0 for padded
        agents; ``trajectories``: ``(B, [N,] A, T, 4)`` states (x, y [m], v [m/s], psi
        [rad]) after each action, in the scene frame, from the current states.
    """
    scene = scene_or_batch if isinstance(scene_or_batch, SceneContext) else None
    if scene is None:
        scene = model.encode(scene_or_batch)
    steps = model.config.future_steps
    if eps is None:
        eps = draw_noise(scene, steps, num_samples, generator)
    batch, agents = scene.agent_mask.shape
    lead = (batch, agents) if num_samples is None else (batch, num_samples, agents)
    if tuple(eps.shape) != (*lead, steps, 2):
        axes = "(B, A, T, 2)" if num_samples is None else "(B, N, A, T, 2)"
        raise ValueError(
            f"eps must have shape {axes} = {(*lead, steps, 2)}, got {tuple(eps.shape)}"
        )
    if num_samples is not None:
        scene = scene.repeat_scenes(num_samples)
        eps = eps.reshape(batch * num_samples, agents, steps, 2)
    a = eps + base_velocity(model, eps, scene)
    actions, trajectories = decode_plans(a, scene.state, scene.agent_mask, normalizer, dynamics)
    if num_samples is not None:
        actions = actions.reshape(*lead, steps, 2)
        trajectories = trajectories.reshape(*lead, steps, 4)
    return actions, trajectories
