"""The two guidance objectives, shared by RiskFlow and the guided baselines.

* ``L_adv`` (:func:`adversarial_loss`): pulls controllable agents toward their targets.
* ``L_map`` (:func:`map_loss`, :class:`MapTerm`): keeps their footprints on the road.

Definitions, sign and weight conventions: :mod:`policies.riskflow.guidance`. Every
guided method (RiskFlow's output-space guidance, the CTG / CTG++ / CCDiff-style
diffusion guidance, STRIVE-style latent optimisation) uses these same functions, so a
comparison between them is a comparison of how they guide, not of what they optimise.
"""

from __future__ import annotations

import torch
from torch import Tensor

from riskflow_env.geometry import footprint_points
from riskflow_env.maps import DrivableMap

__all__ = ["MapTerm", "adversarial_loss", "map_loss"]


def adversarial_loss(xy: Tensor, target_xy: Tensor, horizon: int | None = None) -> Tensor:
    """``L_adv``: summed over agents, mean over ``t < horizon`` of the nearest-target distance.

    Args:
        xy: (C, T, 2) [m] controllable agents' positions.
        target_xy: (J, T, 2) [m] targets' positions.
        horizon: ``T_g`` steps; None: all.

    Returns:
        scalar [m]; 0 if there is no agent or no target.
    """
    xy, target_xy = xy[:, :horizon], target_xy[:, :horizon]
    if xy.shape[0] == 0 or target_xy.shape[0] == 0:
        return xy.sum() * 0.0
    with torch.no_grad():  # the gradient of a min is the gradient at the argmin
        offsets = xy[:, None] - target_xy[None]  # (C, J, T_g, 2)
        nearest = (offsets * offsets).sum(dim=-1).argmin(dim=1)  # (C, T_g)
    steps = torch.arange(xy.shape[1], device=xy.device)
    offset = xy - target_xy.detach()[nearest, steps]  # (C, T_g, 2)
    # vector_norm's gradient is 0 (not NaN) where an agent sits exactly on its target.
    return torch.linalg.vector_norm(offset, dim=-1).sum() / xy.shape[1]


def map_loss(
    trajectories: Tensor,
    length: Tensor,
    width: Tensor,
    drivable_map: DrivableMap,
    frame: Tensor,
    margin: float = 0.2,
    decay: float = 0.98,
) -> Tensor:
    """``L_map``: decayed squared off-road depth of the footprint samples.

    Args:
        trajectories: (C, T, 4) states in the scene frame.
        length: (C,) [m].
        width: (C,) [m].
        drivable_map: the map, world frame.
        frame: (3,) world pose (x [m], y [m], psi [rad]) of the scene frame.
        margin: [m] added to the SDF before the penalty.
        decay: ``w_t = decay ** t``.

    Returns:
        scalar [m^2].
    """
    return MapTerm(drivable_map, frame, length, width, trajectories.shape[1], margin, decay)(
        trajectories
    )


class MapTerm:
    """``L_map`` with its constants (rotation to the world frame, ``w_t``) made once."""

    def __init__(
        self,
        drivable_map: DrivableMap,
        frame: Tensor,
        length: Tensor,
        width: Tensor,
        steps: int,
        margin: float,
        decay: float,
    ) -> None:
        cos, sin = torch.cos(frame[2]), torch.sin(frame[2])
        self.rotation_t = torch.stack([torch.stack([cos, sin]), torch.stack([-sin, cos])])
        self.origin, self.yaw = frame[:2], frame[2]
        # The footprint samples in each vehicle's own frame, (C, 1, 9) along and across [m]
        # (``footprint_points`` at the origin with heading 0: the one definition of them).
        zero = torch.zeros_like(length)
        local = footprint_points(torch.stack([zero, zero], dim=-1), zero, length, width)
        self.along, self.across = local[:, None, :, 0], local[:, None, :, 1]
        self.map, self.margin = drivable_map, margin
        self.weights = decay ** torch.arange(steps, device=frame.device, dtype=frame.dtype)

    def __call__(self, trajectories: Tensor) -> Tensor:
        world = trajectories[..., :2] @ self.rotation_t + self.origin  # (C, T, 2)
        yaw = (trajectories[..., 3] + self.yaw)[..., None]
        cos, sin = torch.cos(yaw), torch.sin(yaw)  # (C, T, 1)
        x = world[..., :1] + cos * self.along - sin * self.across  # (C, T, 9)
        y = world[..., 1:] + sin * self.along + cos * self.across
        points = torch.stack([x, y], dim=-1)  # == footprint_points(world, yaw, ...)
        depth = torch.relu(self.map.sdf_at(points) + self.margin)  # (C, T, 9)
        return ((depth * depth).sum(dim=-1) * self.weights).sum()
