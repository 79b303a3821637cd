"""Ego planners ``riskflow-eval --ego`` can put under test: IDM, constant velocity, log replay,
sampling MPC."""

from __future__ import annotations

import numpy as np

from policies.planners import ConstantVelocityPlanner, EgoPlanner, IDMPlanner, SamplingMPCPlanner
from riskflow_env.agents import ReplayPolicy
from riskflow_env.view import SceneView


class ReplayPlanner:
    """The ego replays its logged future (:class:`~policies.baselines.ReplayPolicy`,
    tracking mode, restricted to the ego); an ``EgoPlanner``."""

    def __init__(self) -> None:
        self.policy = ReplayPolicy(controlled=("ego",))

    def reset(self, view: SceneView) -> None:
        """Take the ego's reference track."""
        self.policy.reset(view)

    def __call__(self, observation: np.ndarray | None, view: SceneView) -> np.ndarray:
        """(2,) (accel [m/s^2], yaw rate [rad/s]); zeros when the ego is not live."""
        return self.policy.act(view).get("ego", np.zeros(2))


EGO_PLANNERS = {
    "idm": IDMPlanner,
    "cv": ConstantVelocityPlanner,
    "replay": ReplayPlanner,
    "mpc": SamplingMPCPlanner,
}


def make_planner(name: str) -> EgoPlanner:
    """A fresh ego planner ``name`` (one of :data:`EGO_PLANNERS`)."""
    if name not in EGO_PLANNERS:
        raise ValueError(f"--ego must be one of {tuple(EGO_PLANNERS)}, got {name!r}")
    return EGO_PLANNERS[name]()
