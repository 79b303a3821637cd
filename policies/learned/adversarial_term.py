"""``L_adv``, the guidance objective's adversarial term: each controllable agent's distance
to its nearest target, averaged over the guidance horizon (the paper's sum over time,
divided by ``T_g``), with its gradient in closed form. Definitions and conventions:
:mod:`policies.learned.guidance_losses` and :mod:`policies.riskflow.guidance`."""

from __future__ import annotations

import torch
from torch import Tensor

from riskflow_env._array import attach_gradient, requires_grad


def adversarial_loss(xy: Tensor, target_xy: Tensor, horizon: int | None = None) -> Tensor:
    """``L_adv``: summed over agents, mean over ``t < horizon`` of the nearest-target
    distance.

    Differentiable with respect to ``xy`` (targets are constants): the value and its
    gradient come from :func:`adversarial_value_and_gradient`.

    Args:
        xy: (C, T, 2) [m] controllable agents' positions.
        target_xy: (J, T, 2) [m] targets' positions.
        horizon: ``T_g`` steps; None: all.

    Returns:
        scalar [m]; 0 if there is no agent or no target.
    """
    if not requires_grad(xy):
        rows, _ = _adversarial(xy, target_xy, horizon, None, False)
        return rows.sum()
    value, gradient = adversarial_value_and_gradient(xy, target_xy, horizon)
    return attach_gradient(value, xy, gradient, axis=None)


def adversarial_value_and_gradient(
    xy: Tensor, target_xy: Tensor, horizon: int | None = None
) -> tuple[Tensor, Tensor]:
    """:func:`adversarial_loss` [m] and its gradient (C, T, 2) [m/m] with respect to ``xy``.

    The gradient of a min is the gradient at the argmin: at each ``t < T_g`` the unit
    vector from the nearest target to the agent (0 where the agent sits exactly on it)
    divided by ``T_g``; 0 beyond ``T_g``. No autograd graph is built.
    """
    values, gradient = adversarial_rows(xy, target_xy, horizon)
    return values.sum(), gradient


def adversarial_rows(
    xy: Tensor,
    target_xy: Tensor,
    horizon: int | None = None,
    target_valid: Tensor | None = None,
    with_gradient: bool = True,
) -> tuple[Tensor, Tensor | None]:
    """``L_adv`` of each controllable agent and its gradient, each with its own targets.

    Batched planning guides the rows of several scenes at once: each row is pulled toward
    the targets of its own scene (padded to J, ``target_valid`` marks the real ones).

    Args:
        xy: (C, T, 2) [m] controllable agents' positions.
        target_xy: (J, T, 2) [m] targets shared by every row, or (C, J, T, 2) per row.
        horizon: ``T_g`` steps; None: all.
        target_valid: None (every target), or (C, J) bool, the targets of each row.
        with_gradient: also return the gradient (C, T, 2) [m/m] (else None).

    Returns:
        (C,) [m] each row's mean nearest-target distance (0 for a row
        without target) and its gradient; no autograd graph is built.
    """
    return _adversarial(xy.detach(), target_xy, horizon, target_valid, with_gradient)


def _adversarial(
    xy: Tensor,
    target_xy: Tensor,
    horizon: int | None,
    target_valid: Tensor | None,
    with_gradient: bool,
) -> tuple[Tensor, Tensor | None]:
    """The one implementation of :func:`adversarial_rows` (and so of the loss)."""
    near, target_xy = xy[:, :horizon], target_xy[..., :horizon, :].detach()
    if near.shape[0] == 0 or target_xy.shape[-3] == 0:
        zero = near.new_zeros(near.shape[0])
        return zero, torch.zeros_like(xy) if with_gradient else None
    with torch.no_grad():
        per_row = target_xy if target_xy.ndim == 4 else target_xy[None]
        dx = near[:, None, :, 0] - per_row[..., 0]  # (C, J, T_g)
        dy = near[:, None, :, 1] - per_row[..., 1]
        squared = dx * dx + dy * dy
        if target_valid is not None:
            squared.masked_fill_(~target_valid[..., None], torch.inf)
        # min over the middle axis (values and indices): several times argmin's speed.
        nearest = squared.min(dim=1, keepdim=True).indices  # (C, 1, T_g)
    offset = torch.stack([dx.gather(1, nearest)[:, 0], dy.gather(1, nearest)[:, 0]], dim=-1)
    distance = torch.linalg.vector_norm(offset, dim=-1)  # (C, T_g)
    if target_valid is not None:  # rows without a target: 0
        distance = distance * target_valid.any(dim=1, keepdim=True).to(distance.dtype)
    steps = near.shape[1]
    values = distance.sum(dim=1) / steps  # the mean over time: each step weighs 1 / T_g
    if not with_gradient:
        return values, None
    scale = torch.where(distance > 0, distance * steps, torch.inf)  # 0 on a target
    gradient = torch.zeros_like(xy)
    gradient[:, :steps] = offset / scale[..., None]
    return values, gradient


__all__ = ["adversarial_loss", "adversarial_rows", "adversarial_value_and_gradient"]
