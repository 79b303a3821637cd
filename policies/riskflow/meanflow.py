"""The MeanFlow objective in action space, with RiskFlow's trajectory-space loss.

Notation (docs/GENERATOR.md; noise at t = 0, data at t = 1), per agent plan:

* ``a*``: normalised ground-truth actions ``(B, A, T, 2)``; ``eps ~ N(0, I)`` alike;
* ``z_t = (1 - t) eps + t a*`` and ``v = a* - eps`` (the conditional velocity);
* ``u = u_theta(z_t, t, r; C)`` the average velocity from ``t`` to ``r >= t``.

MeanFlow identity (Geng et al. 2025, eq. 6, in this convention)::

    u(z_t, t, r) = v(z_t, t) - (t - r) du/dt,   du/dt = v . d_z u + d_t u

``du/dt`` is the Jacobian-vector product of ``u_theta`` with tangents ``(dz, dt, dr) =
(v, 1, 0)``, computed with ``torch.func.jvp`` in the same pass as ``u``; the scene
context ``C`` does not depend on ``(z, t, r)`` and is computed once, outside the JVP.
The MeanFlow target ``u_tgt = v - (t - r) sg(du/dt)`` would be regressed directly; the
RiskFlow paper instead reconstructs the action plan::

    a_hat = eps + u + (t - r) * clip(sg(du/dt), -c, c),   c = 0.03

(``a_hat - a* = u - u_tgt`` before clipping), de-normalises it, rolls it out through
``riskflow_env.dynamics.rollout`` from every agent's current state and minimises the
masked squared error to the ground-truth future positions (optionally headings).
Gradients flow through ``u`` only.

Caveat: ``rollout`` clips actions to the dynamics bounds, so a reconstructed action
beyond a bound gets no gradient through that step; and positions integrate the actions
twice, so they barely constrain high-frequency action errors. ``metrics["action_mse"]``
(the plain action-space MeanFlow error) shows both; ``action_weight > 0`` adds it to the
loss.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol

import torch
from torch import Tensor

from policies.riskflow.encoder import SceneContext
from policies.riskflow.generator import RiskFlowGenerator
from policies.riskflow.plan_penalties import offroad_penalty, overlap_penalty
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout, wrap_angle

DUDT_CLIP = 0.03  # c: bound of sg(du/dt) in the reconstruction (RiskFlow paper).
LOSS_KEYS = ("future", "future_valid", "actions", "actions_valid")


class Normalizer(Protocol):
    """Per-channel action normalisation (``policies.riskflow.data.ActionNormalizer``)."""

    def normalize(self, actions: Tensor) -> Tensor:
        """Physical ``(..., 2)`` (accel [m/s^2], yaw rate [rad/s]) -> normalised."""
        ...

    def denormalize(self, actions: Tensor) -> Tensor:
        """Normalised ``(..., 2)`` -> physical units."""
        ...


def _time_as(t: Tensor) -> Tensor:
    """``t (B,)`` or ``(B, A)`` reshaped to broadcast against ``x (B, A, T, 2)``."""
    return t.reshape(t.shape[0], -1, 1, 1)


def _check(batch: Mapping[str, Tensor], eps: Tensor, t: Tensor, r: Tensor) -> None:
    missing = [key for key in LOSS_KEYS if key not in batch]
    if missing:
        raise KeyError(f"batch lacks training key(s) {missing}; see docs/WINDOWS.md")
    if tuple(eps.shape) != tuple(batch["actions"].shape):
        raise ValueError(
            f"eps must have the shape of batch['actions'] (B, A, T, 2) = "
            f"{tuple(batch['actions'].shape)}, got {tuple(eps.shape)}"
        )
    batch_size = eps.shape[0]
    for name, time in (("t", t), ("r", r)):
        if time.shape not in ((batch_size,), tuple(eps.shape[:2])):
            raise ValueError(f"{name} must be (B,) or (B, A), got {tuple(time.shape)}")
    if bool((r < t).any()):
        raise ValueError("the MeanFlow times need t <= r (noise at 0, data at 1)")


def average_velocity_jvp(
    u_fn: Callable[[Tensor, Tensor, Tensor], Tensor], z_t: Tensor, t: Tensor, r: Tensor, v: Tensor
) -> tuple[Tensor, Tensor]:
    """``u = u_fn(z_t, t, r)`` and its total derivative along the flow, in one pass.

    ``du/dt = v . d_z u + d_t u`` is the JVP of ``u_fn`` with tangents ``(dz, dt, dr) =
    (v, 1, 0)`` (MeanFlow, Geng et al. 2025, eq. 8), by forward-mode AD
    (``torch.func.jvp``). ``u`` keeps its autograd graph; ``du/dt`` should be
    detached by the caller (the stop-gradient of the MeanFlow target).

    Args:
        u_fn: ``(z, t, r) -> u``, e.g. the MeanFlow head with a fixed context.
        z_t: ``(B, ...)`` point on the path.
        t: ``(B,)`` (or ``(B, A)``) times.
        r: like ``t``.
        v: like ``z_t``, the velocity ``dz_t/dt`` (``a* - eps`` in training).

    Returns:
        ``(u, du/dt)``, both shaped like ``u_fn``'s output.
    """
    return torch.func.jvp(u_fn, (z_t, t, r), (v, torch.ones_like(t), torch.zeros_like(r)))


def meanflow_target(v: Tensor, dudt: Tensor, t: Tensor, r: Tensor) -> Tensor:
    """MeanFlow identity target ``u_tgt = v - (t - r) du/dt`` (Geng et al. 2025, eq. 6/10).

    ``t, r`` must broadcast against ``v`` (e.g. ``(B, 1, 1, 1)``). Equals the true
    average velocity when ``v`` is the marginal velocity and ``du/dt`` is exact.
    """
    return v - (t - r) * dudt


def target_actions(batch: Mapping[str, Tensor], normalizer: Normalizer) -> Tensor:
    """``a*``: normalised ``batch["actions"]``, 0 (the mean action) where not valid."""
    valid = batch["actions_valid"].bool()[..., None]
    return torch.where(valid, normalizer.normalize(batch["actions"]), 0.0)


def trajectory_loss(
    a_hat: Tensor,
    batch: Mapping[str, Tensor],
    scene: SceneContext,
    normalizer: Normalizer,
    heading_weight: float = 0.0,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
    collision_weight: float = 0.0,
    offroad_weight: float = 0.0,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Masked squared error of the rolled-out reconstruction to the reference future,
    plus the optional realism penalties of :mod:`policies.riskflow.plan_penalties`.

    Args:
        a_hat: ``(B, A, T, 2)`` normalised reconstructed actions.
        batch: ``future (B, A, T, 4)``, ``future_valid (B, A, T)`` (scene frame).
        scene: the encoder output (current states and agent mask).
        normalizer: action normalisation.
        heading_weight: weight [m^2/rad^2] of ``heading_mse`` in the loss.
        dynamics: time step and bounds of the rollout.
        collision_weight: weight of ``overlap`` (squared penetration depth of decoded box
            pairs [m^2]); needs ``length``, ``width`` in the batch.
        offroad_weight: weight of ``offroad`` (squared excess of the planned centres'
            SDF [m^2], from ``map_crops``).

    Returns:
        ``loss = position_mse + heading_weight * heading_mse + collision_weight *
        overlap + offroad_weight * offroad`` (means over valid agent steps, per step:
        ``|p_hat - p|^2`` [m^2]) and detached metrics ``position_mse``, ``heading_mse``
        [rad^2], ``ade`` [m], ``fde`` [m] (at the last valid step), and ``overlap`` /
        ``offroad`` when their weight is not 0.
    """
    trajectory = rollout(scene.state, normalizer.denormalize(a_hat), dynamics)  # (B, A, T, 4)
    future = batch["future"]
    mask = batch["future_valid"].bool() & scene.agent_mask[..., None]
    weight = mask.to(a_hat.dtype)
    count = weight.sum().clamp(min=1.0)
    squared = ((trajectory[..., :2] - future[..., :2]) ** 2).sum(dim=-1)  # (B, A, T) [m^2]
    heading = wrap_angle(trajectory[..., 3] - future[..., 3]) ** 2
    position_mse = (squared * weight).sum() / count
    heading_mse = (heading * weight).sum() / count
    loss = position_mse + heading_weight * heading_mse
    penalties = {}
    if collision_weight:
        penalties["overlap"] = overlap_penalty(trajectory, batch, mask)
        loss = loss + collision_weight * penalties["overlap"]
    if offroad_weight:
        penalties["offroad"] = offroad_penalty(trajectory, batch, scene.state, mask)
        loss = loss + offroad_weight * penalties["offroad"]
    with torch.no_grad():
        distance = squared.detach().sqrt()
        steps = torch.arange(mask.shape[-1], device=mask.device)
        last = torch.where(mask, steps, -1).max(dim=-1).values  # (B, A), -1: none valid
        has_last = last >= 0
        final = distance.gather(-1, last.clamp(min=0)[..., None])[..., 0]
        metrics = {
            "position_mse": position_mse.detach(),
            "heading_mse": heading_mse.detach(),
            "ade": (distance * weight).sum() / count,
            "fde": (final * has_last).sum() / has_last.sum().clamp(min=1),
        } | {name: value.detach() for name, value in penalties.items()}
    return loss, metrics


def meanflow_loss(
    model: RiskFlowGenerator,
    batch: Mapping[str, Tensor],
    normalizer: Normalizer,
    eps: Tensor,
    t: Tensor,
    r: Tensor,
    clip: float = DUDT_CLIP,
    heading_weight: float = 0.0,
    action_weight: float = 0.0,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
    collision_weight: float = 0.0,
    offroad_weight: float = 0.0,
) -> tuple[Tensor, dict[str, Tensor]]:
    """RiskFlow's MeanFlow objective (see the module docstring).

    Args:
        model: the generator.
        batch: training windows (``docs/WINDOWS.md``), with the future keys.
        normalizer: action normalisation (``normalize`` / ``denormalize``).
        eps: ``(B, A, T, 2)`` standard normal noise.
        t: ``(B,)`` or ``(B, A)`` start times in [0, 1] (``time_sampler.TimeSampler``).
        r: like ``t``, end times ``r >= t``.
        clip: ``c``, bound of ``sg(du/dt)`` in the reconstruction.
        heading_weight: weight [m^2/rad^2] of ``heading_mse`` in the loss.
        action_weight: weight of ``action_mse`` in the loss (0: RiskFlow's pure
            trajectory-space loss). Positions integrate actions twice, so they barely
            see high-frequency action errors; this term (the MeanFlow regression
            itself) pins those down.
        dynamics: time step and bounds of the rollout.
        collision_weight, offroad_weight: weights of the realism penalties
            (:func:`trajectory_loss`).

    Returns:
        ``(loss, metrics)``: the scalar loss and detached scalar metrics: those of
        :func:`trajectory_loss`, ``loss``, ``action_mse`` (normalised ``|a_hat - a*|^2``
        on valid actions: MeanFlow's own regression error), ``dudt_abs`` (mean
        ``|du/dt|``) and ``dudt_clipped`` (share of entries beyond ``clip``).
    """
    _check(batch, eps, t, r)
    scene = model.encode(batch)
    a_star = target_actions(batch, normalizer)
    t_, r_ = _time_as(t), _time_as(r)
    z_t = (1.0 - t_) * eps + t_ * a_star
    v = a_star - eps

    def u_theta(z: Tensor, t_in: Tensor, r_in: Tensor) -> Tensor:
        return model.average_velocity(z, t_in, r_in, scene)

    u, dudt = average_velocity_jvp(u_theta, z_t, t, r, v)
    dudt = dudt.detach()
    a_hat = eps + u + (t_ - r_) * dudt.clamp(-clip, clip)
    penalties = {"collision_weight": collision_weight, "offroad_weight": offroad_weight}
    loss, metrics = _loss(
        a_hat, a_star, batch, scene, normalizer, heading_weight, action_weight, dynamics,
        **penalties,
    )  # fmt: skip
    metrics["dudt_abs"] = dudt.abs().mean()
    metrics["dudt_clipped"] = (dudt.abs() > clip).to(dudt.dtype).mean()
    return loss, metrics


def flow_matching_loss(
    model: RiskFlowGenerator,
    batch: Mapping[str, Tensor],
    normalizer: Normalizer,
    eps: Tensor,
    t: Tensor,
    heading_weight: float = 0.0,
    action_weight: float = 0.0,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
    collision_weight: float = 0.0,
    offroad_weight: float = 0.0,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Plain flow matching (``r = t``, no JVP): ``a_hat = eps + u_theta(z_t, t, t; C)``.

    The reference the MeanFlow objective is compared with (speed benchmark,
    ablations); same arguments and metrics as :func:`meanflow_loss` without the
    ``du/dt`` ones.
    """
    _check(batch, eps, t, t)
    scene = model.encode(batch)
    a_star = target_actions(batch, normalizer)
    t_ = _time_as(t)
    u = model.average_velocity((1.0 - t_) * eps + t_ * a_star, t, t, scene)
    penalties = {"collision_weight": collision_weight, "offroad_weight": offroad_weight}
    return _loss(
        eps + u, a_star, batch, scene, normalizer, heading_weight, action_weight, dynamics,
        **penalties,
    )  # fmt: skip


def _loss(
    a_hat: Tensor,
    a_star: Tensor,
    batch: Mapping[str, Tensor],
    scene: SceneContext,
    normalizer: Normalizer,
    heading_weight: float,
    action_weight: float,
    dynamics: DynamicsConfig,
    **penalties: float,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Trajectory loss (with its penalties) plus ``action_weight * action_mse``."""
    loss, metrics = trajectory_loss(
        a_hat, batch, scene, normalizer, heading_weight, dynamics, **penalties
    )
    weight = (batch["actions_valid"].bool() & scene.agent_mask[..., None]).to(a_hat.dtype)
    squared = ((a_hat - a_star) ** 2).sum(dim=-1)
    action_mse = (squared * weight).sum() / weight.sum().clamp(min=1.0)
    if action_weight:
        loss = loss + action_weight * action_mse
    metrics["action_mse"] = action_mse.detach()
    metrics["loss"] = loss.detach()
    return loss, metrics
