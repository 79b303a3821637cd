"""``L_sep``, the third term of the guidance objective every guided adversary shares
(:class:`~policies.learned.guidance_losses.ObjectiveConfig`, ``lambda_sep``): the summed
squared penetration depth of every pair of guided boxes of a scene over the guidance
horizon, so that the guided vehicles do not converge on each other, and of every guided
box with a **bystander** of its scene (a present vehicle that is neither the ego nor
guided nor a target: with target ``"ego"``, the vehicles that keep their unguided plans),
whose plan is held fixed, so that an attacker aimed at the ego does not strike a third
vehicle on its way. Not in the RiskFlow paper's objective (``lambda_sep = 0`` drops it):
without it several guided vehicles converge on one target as a swarm.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from policies.learned.guidance_losses import ObjectiveConfig
from policies.learned.plan_overlap import overlap_gradient

__all__ = ["Separation", "separation_term"]


class Separation:
    """The gradient of ``L_sep`` (module docstring) with respect to the guided
    rows' trajectories: the summed squared penetration depth of every pair of guided boxes
    of one scene, and of every guided box with every bystander of its scene (fixed plans),
    over the first ``horizon`` steps, in closed form
    (:func:`~policies.learned.plan_overlap.overlap_gradient`, the avoidance steps'
    objective). Shared by output-space guidance, STRIVE-style's latent optimisation and
    the diffusion baselines' guidance.

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
