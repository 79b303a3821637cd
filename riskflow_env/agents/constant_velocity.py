"""Constant velocity: every controlled vehicle keeps its speed and heading."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from riskflow_env.agents.base import actions_dict, controlled_mask
from riskflow_env.view import SceneView


class ConstantVelocityPolicy:
    """Zero acceleration and zero yaw rate for every controlled live vehicle.

    Args:
        controlled: ``"others"`` (every vehicle but the ego), ``"all"``, or agent names.
    """

    def __init__(self, controlled: str | Sequence[str] = "others") -> None:
        self.controlled = controlled

    def reset(self, view: SceneView) -> None:
        """Nothing to prepare."""

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """``{agent: (0 [m/s^2], 0 [rad/s])}`` for the controlled live agents."""
        mask = controlled_mask(view, self.controlled)
        return actions_dict(view, mask, np.zeros((view.num_agents, 2)))
