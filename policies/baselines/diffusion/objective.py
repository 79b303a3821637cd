"""Training objective of the diffusion denoiser (``riskflow-train --generator diffusion``).

DDPM training (Ho et al. 2020): a level ``k ~ U{0, .., K-1}`` per scene, noise ``eps``,
``x_k = sqrt(alpha_bar_k) a* + sqrt(1 - alpha_bar_k) eps`` from the normalised
ground-truth actions ``a*`` (``policies.learned.trajectory_loss.target_actions``), one pass of
the denoiser, and

* ``prediction="v"`` (default) or ``"sample"`` (CTG-like): RiskFlow's *same* reconstruction loss on
  ``x0_hat``: the trajectory-space error of ``rollout(denorm(x0_hat))`` against the
  reference future (``policies.learned.trajectory_loss``) plus ``weights.action`` times the
  normalised action error, exactly what ``meanflow_loss`` puts on its ``a_hat``, so
  the two generators differ in how they generate, not in what they are fit to;
* ``prediction="epsilon"``: the "simple" loss ``|eps_hat - eps|^2`` (Ho et al. 2020).

No JVP is needed: one step costs one encoder and one head pass, like flow matching.
"""

from __future__ import annotations

import torch
from torch import Tensor

from policies.baselines.diffusion.model import DiffusionDenoiser
from policies.learned.data import Normalizer
from policies.learned.trajectory_loss import (
    LossWeights,
    action_mse,
    target_actions,
    trajectory_loss,
)
from policies.learned.window_types import WindowBatch
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import DEFAULT_CONFIG

DEFAULT_WEIGHTS = LossWeights(action=1.0)  # the reconstruction's action error at weight 1


def draw_levels(
    batch_size: int, num_steps: int, generator: torch.Generator | None, device: torch.device | str
) -> Tensor:
    """``(B,)`` levels, uniform on ``{0, .., num_steps - 1}``."""
    return torch.randint(0, num_steps, (batch_size,), generator=generator, device=device)


def diffusion_loss(
    denoiser: DiffusionDenoiser,
    batch: WindowBatch,
    normalizer: Normalizer,
    eps: Tensor,
    k: Tensor,
    weights: LossWeights = DEFAULT_WEIGHTS,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> tuple[Tensor, dict[str, Tensor]]:
    """The denoiser's training loss (module docstring).

    Args:
        denoiser: the denoiser (its network is what is trained).
        batch: training windows (``docs/how-to/windows.md``) with the future fields.
        normalizer: action normalisation.
        eps: ``(B, A, T, 2)`` standard normal noise.
        k: ``(B,)`` int levels in ``[0, K)`` (:func:`draw_levels`).
        weights: of the reconstruction loss on the decoded ``x0_hat`` (not with
            ``"epsilon"``): its action error, heading error and realism penalties.
        dynamics: time step and bounds of the rollout.

    Returns:
        ``(loss, metrics)``: detached scalars ``loss``, ``action_mse`` (normalised
        ``|x0_hat - a*|^2``), ``eps_mse``, and ``trajectory_loss``'s ``position_mse``,
        ``heading_mse``, ``ade``, ``fde`` of ``x0_hat``.
    """
    batch.require_future("the diffusion loss")
    if tuple(eps.shape) != tuple(batch.actions.shape):
        raise ValueError(
            f"eps must have the shape of batch.actions {tuple(batch.actions.shape)}, "
            f"got {tuple(eps.shape)}"
        )
    num_steps = denoiser.diffusion.num_steps
    if k.shape != eps.shape[:1] or bool((k < 0).any()) or bool((k >= num_steps).any()):
        raise ValueError(f"k must be (B,) levels in [0, {num_steps}), got {k}")
    scene = denoiser.encode(batch)
    a_star = target_actions(batch, normalizer)
    x_k = denoiser.schedule.q_sample(a_star, k, eps)
    x0_hat, eps_hat = denoiser(x_k, k, scene)
    action_error = action_mse(x0_hat, a_star, batch, scene)
    eps_mse = action_mse(eps_hat, eps, batch, scene)
    if denoiser.diffusion.prediction != "epsilon":
        loss, metrics = trajectory_loss(x0_hat, batch, scene, normalizer, weights, dynamics)
        loss = loss + weights.action * action_error
    else:
        with torch.no_grad():
            _, metrics = trajectory_loss(x0_hat, batch, scene, normalizer, dynamics=dynamics)
        loss = eps_mse
    metrics |= {
        "loss": loss.detach(),
        "action_mse": action_error.detach(),
        "eps_mse": eps_mse.detach(),
    }
    return loss, metrics


__all__ = ["DEFAULT_WEIGHTS", "diffusion_loss", "draw_levels"]
