"""Maneuver-clearance features: what a few fixed maneuvers would lead to, for the RL ego.

The ego's observation (:mod:`riskflow_env.observations`) lists its neighbours' relative
positions and velocities; turning that into "which way out is free" is what a sampling
planner does in one vectorised rollout and what PPO has to discover from collisions.
:class:`ManeuverFeatures` hands the policy that summary: for each of a few maneuvers
(brake / hold / accelerate, each straight or as a lane change to either side), the
smallest predicted separation from any other vehicle and the largest map SDF of the
footprint over the next 3 s, under constant-velocity predictions of the others, computed
by :class:`~policies.planners.SamplingMPCPlanner` (one implementation). It uses nothing
a real ego cannot see (current states and the map), not the adversary's plans.

The features are appended to the observation by
:class:`~policies.rl.envs.EgoTrainingEnv` (``maneuver_features=True``) and, identically,
by :class:`~policies.rl.evaluation.PPOPlanner` at evaluation.
"""

from __future__ import annotations

import numpy as np

from policies.planners.sampling_mpc import SamplingMPCPlanner, candidate_actions
from riskflow_env.config import DynamicsConfig
from riskflow_env.view import SceneView

ACCELS = (-5.0, 0.0, 3.0)  # [m/s^2] brake, hold, accelerate
TURNS = (-0.15, 0.0, 0.15)  # [rad/s] right, straight, left
LANE_CHANGE_STEPS = 15  # [steps] each way of the lane-change shape
CAP = 10.0  # [m] features are clipped to [-CAP, CAP]
MANEUVER_SETS = ("compact", "mpc")


def maneuvers(horizon: int = 30, maneuver_set: str = "compact") -> np.ndarray:
    """(M, horizon, 2) the fixed maneuvers (accel [m/s^2], yaw rate [rad/s] per step).

    ``"compact"`` (M = 15): brake / hold / accelerate, each straight, as a lane change to
    either side or as a constant turn to either side. ``"mpc"`` (M = 200): the sampling
    MPC's own candidate set (:func:`~policies.planners.sampling_mpc.candidate_actions`,
    finer accelerations, yaw rates and lane-change durations). They are what
    :class:`ManeuverFeatures` describes and what a policy with ``maneuver_actions``
    chooses among."""
    if maneuver_set == "compact":
        return candidate_actions(horizon, ACCELS, TURNS, (LANE_CHANGE_STEPS,))
    if maneuver_set == "mpc":
        return candidate_actions(horizon)
    raise ValueError(f"maneuver_set must be one of {MANEUVER_SETS}, got {maneuver_set!r}")


class ManeuverFeatures:
    """Predicted clearance and road margin of fixed maneuvers (module docstring).

    Args:
        horizon: look-ahead [steps].
        dynamics: the env's dynamics.
        maneuver_set: which maneuvers (:func:`maneuvers`).
    """

    def __init__(
        self,
        horizon: int = 30,
        dynamics: DynamicsConfig | None = None,
        maneuver_set: str = "compact",
    ) -> None:
        candidates = maneuvers(horizon, maneuver_set)
        self.planner = SamplingMPCPlanner(horizon=horizon, dynamics=dynamics, candidates=candidates)
        self.size = 2 * len(candidates)

    def __call__(self, view: SceneView) -> np.ndarray:
        """(size,) float32: per maneuver, the smallest separation [m] from any predicted
        vehicle, then the largest footprint SDF [m] (positive: off the road), each
        clipped to [-10, 10] m."""
        _, gap, edge = self.planner.outcomes(view, exact_below=CAP)
        features = np.concatenate([gap.min(axis=-1), edge.max(axis=-1)])
        return np.clip(features, -CAP, CAP).astype(np.float32)

    def augment(self, observation: np.ndarray, view: SceneView) -> np.ndarray:
        """``observation`` with the features of ``view`` appended."""
        return np.concatenate([np.asarray(observation, dtype=np.float32), self(view)])
