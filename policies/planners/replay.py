"""The ego replays its log: a reference planner (what the recorded driver did)."""

from __future__ import annotations

import numpy as np

from riskflow_env.agents import ReplayPolicy
from riskflow_env.view import SceneView


class ReplayPlanner:
    """The ego replays its logged future (:class:`~riskflow_env.agents.ReplayPolicy`,
    tracking mode, restricted to the ego); an ``EgoPlanner``."""

    def __init__(self) -> None:
        self.policy = ReplayPolicy(controlled=("ego",))

    def reset(self, view: SceneView) -> None:
        """Take the ego's reference track."""
        self.policy.reset(view)

    def __call__(self, observation: np.ndarray | None, view: SceneView) -> np.ndarray:
        """(2,) (accel [m/s^2], yaw rate [rad/s]); zeros when the ego is not live."""
        return self.policy.act(view).get("ego", np.zeros(2))
