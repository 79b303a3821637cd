"""``L_sep``, the third term of the guidance objective every guided adversary shares
(:class:`~policies.learned.guidance_losses.ObjectiveConfig`, ``lambda_sep``): the summed
squared penetration depth of every pair of guided boxes of a scene over the guidance
horizon, so that the guided vehicles do not converge on each other. Not in the RiskFlow
paper's objective (``lambda_sep = 0`` drops it): without it several guided vehicles
converge on one target as a swarm.
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
    of one scene over the first ``horizon`` steps, in closed form
    (:func:`~policies.learned.plan_overlap.overlap_gradient`, the avoidance steps'
    objective). Shared by output-space guidance, STRIVE-style's latent optimisation and
    the diffusion baselines' guidance.

    Args:
        length, width: (C,) [m] of the guided rows.
        scene_of_row: (C,) the scene of each row (pairs are taken within a scene).
        horizon: ``T_g`` steps; None: the whole plan.
    """

    def __init__(
        self, length: Tensor, width: Tensor, scene_of_row: Tensor, horizon: int | None
    ) -> None:
        pairs = (scene_of_row[:, None] == scene_of_row[None, :]).triu(diagonal=1)
        self.boxes = (length[None], width[None], pairs[None])  # one "scene" of C boxes
        self.horizon = horizon

    def gradient(self, trajectories: Tensor) -> Tensor:
        """(C, T, 4) ``d L_sep / d trajectories`` of (C, T, 4) states (zero beyond the
        horizon and in the speed channel)."""
        gradient = torch.zeros_like(trajectories)
        near = trajectories[None, None, :, : self.horizon].detach()  # (1, 1, C, T_g, 4)
        gradient[:, : self.horizon] = overlap_gradient(near, *self.boxes)[0][0, 0]
        return gradient


def separation_term(
    scene: Any, rows: Tensor, config: ObjectiveConfig, scene_of_row: Tensor | None = None
) -> Separation | None:
    """``L_sep`` of the ``rows`` of ``scene`` (anything with (N,) ``length`` and ``width``
    [m]; ``rows`` (C,) index them), or None when ``config.lambda_sep`` is 0;
    ``scene_of_row`` (C,) the scene of each row (None: one scene), as for
    :func:`~policies.learned.guidance_losses.map_term`."""
    if not config.lambda_sep:
        return None
    same = torch.zeros_like(rows) if scene_of_row is None else scene_of_row
    return Separation(scene.length[rows], scene.width[rows], same, config.horizon)
