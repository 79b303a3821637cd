"""``L_adv``, the guidance objective's adversarial term: each controllable agent's distance
to its nearest target, reduced over the guidance horizon by the mean (the paper's sum over
time, divided by ``T_g``) or a soft minimum (``adv_temperature``), with its gradient in
closed form. Definitions and conventions: :mod:`policies.learned.guidance_losses` and
:mod:`policies.riskflow.guidance`."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from riskflow_env._array import attach_gradient, requires_grad


def adversarial_loss(
    xy: Tensor, target_xy: Tensor, horizon: int | None = None, temperature: float | None = None
) -> Tensor:
    """``L_adv``: summed over agents, mean (or soft minimum) over ``t < horizon`` of the
    nearest-target distance.

    Differentiable with respect to ``xy`` (targets are constants): the value and its
    gradient come from :func:`adversarial_value_and_gradient`.

    Args:
        xy: (C, T, 2) [m] controllable agents' positions.
        target_xy: (J, T, 2) [m] targets' positions.
        horizon: ``T_g`` steps; None: all.
        temperature: None (the mean over time: the paper's sum divided by ``T_g``) or the
            soft minimum's ``tau`` [m] (:class:`ObjectiveConfig`'s ``adv_temperature``).

    Returns:
        scalar [m]; 0 if there is no agent or no target.
    """
    if not requires_grad(xy):
        rows, _ = _adversarial(xy, target_xy, horizon, None, False, temperature)
        return rows.sum()
    value, gradient = adversarial_value_and_gradient(xy, target_xy, horizon, temperature)
    return attach_gradient(value, xy, gradient, axis=None)


def adversarial_value_and_gradient(
    xy: Tensor, target_xy: Tensor, horizon: int | None = None, temperature: float | None = None
) -> tuple[Tensor, Tensor]:
    """:func:`adversarial_loss` [m] and its gradient (C, T, 2) [m/m] with respect to ``xy``.

    The gradient of a min is the gradient at the argmin: at each ``t < T_g`` the unit
    vector from the nearest target to the agent (0 where the agent sits exactly on it)
    times the step's weight, ``1 / T_g`` for the mean and ``softmax_t(-d / tau)`` for the
    soft minimum; 0 beyond ``T_g``. No autograd graph is built.
    """
    values, gradient = adversarial_rows(xy, target_xy, horizon, temperature=temperature)
    return values.sum(), gradient


def adversarial_rows(
    xy: Tensor,
    target_xy: Tensor,
    horizon: int | None = None,
    target_valid: Tensor | None = None,
    with_gradient: bool = True,
    temperature: float | None = None,
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
        temperature: None (the mean over time) or the soft minimum's ``tau`` [m].

    Returns:
        (C,) [m] each row's mean (or soft-minimum) nearest-target distance (0 for a row
        without target) and its gradient; no autograd graph is built.
    """
    return _adversarial(xy.detach(), target_xy, horizon, target_valid, with_gradient, temperature)


def _adversarial(
    xy: Tensor,
    target_xy: Tensor,
    horizon: int | None,
    target_valid: Tensor | None,
    with_gradient: bool,
    temperature: float | None = None,
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
    if temperature is None:  # the mean over time: each step weighs 1 / T_g
        values = distance.sum(dim=1) / steps
    else:  # -tau log mean_t exp(-d_t / tau): each step weighs w_t = softmax_t(-d / tau)
        logits = distance / -temperature
        values = -temperature * (torch.logsumexp(logits, dim=1) - math.log(steps))
        if target_valid is not None:  # rows without a target: 0, not -tau * rounding
            values = values * target_valid.any(dim=1).to(values.dtype)
    if not with_gradient:
        return values, None
    if temperature is None:
        scale = distance * steps
    else:
        scale = distance / torch.softmax(logits, dim=1)  # d_t / w_t
    scale = torch.where(distance > 0, scale, torch.inf)  # 0 on a target
    gradient = torch.zeros_like(xy)
    gradient[:, :steps] = offset / scale[..., None]
    return values, gradient


__all__ = ["adversarial_loss", "adversarial_rows", "adversarial_value_and_gradient"]
