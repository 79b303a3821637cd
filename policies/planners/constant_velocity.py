"""Constant-velocity ego planner: keep speed and heading, whatever happens.

The weakest sensible planner, a floor for stress tests: it never brakes and never steers.
"""

from __future__ import annotations

import numpy as np

from riskflow_env.view import SceneView


class ConstantVelocityPlanner:
    """Zero acceleration and zero yaw rate; an ``EgoPlanner``."""

    def reset(self, view: SceneView) -> None:
        """Nothing to prepare."""

    def __call__(self, observation: np.ndarray | None, view: SceneView | None = None) -> np.ndarray:
        """(2,) zeros: (0 [m/s^2], 0 [rad/s])."""
        return np.zeros(2)
