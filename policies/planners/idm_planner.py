"""IDM ego planner: lane following with car following and yielding, for the ego alone.

It is :class:`~riskflow_env.agents.idm.IDMPolicy` restricted to one vehicle (one
implementation of IDM in the code base): each step the ego is matched to a lane of the
map's lane graph and steers with pure pursuit toward a point ahead along it (taking, at
forks, the lanes of its logged route: the ego's reference future plays the part of a
route planner's output); its acceleration is the IDM acceleration toward its desired
speed, with the nearest vehicle ahead in its corridor, the end of a dead-end lane and
predicted crossing conflicts as leaders (it yields to every other vehicle). See
:mod:`riskflow_env.agents.idm` for the details and :class:`~riskflow_env.agents.idm.IDMParams`
for the parameters.
"""

from __future__ import annotations

import numpy as np

from riskflow_env.agents.idm import IDMParams, IDMPolicy
from riskflow_env.config import DynamicsConfig
from riskflow_env.view import SceneView


class IDMPlanner:
    """IDM lane following for one agent (the ego by default); an ``EgoPlanner``.

    Args:
        params: IDM and lane-keeping parameters (default :class:`IDMParams`).
        dynamics: the env's dynamics bounds; actions are clipped to them.
        agent: the agent it drives.
    """

    def __init__(
        self,
        params: IDMParams | None = None,
        dynamics: DynamicsConfig | None = None,
        agent: str = "ego",
    ) -> None:
        self.agent = agent
        self.policy = IDMPolicy(controlled=(agent,), params=params, dynamics=dynamics)

    def reset(self, view: SceneView) -> None:
        """Lane graph, route and desired speed of the new episode."""
        self.policy.reset(view)

    def __call__(self, observation: np.ndarray | None, view: SceneView) -> np.ndarray:
        """(2,) (accel [m/s^2], yaw rate [rad/s]); zeros when the agent is not live.

        Args:
            observation: unused (the planner reads the scene view).
            view: the current scene.
        """
        return self.policy.act(view).get(self.agent, np.zeros(2))


class LaneKeepingPlanner(IDMPlanner):
    """The IDM planner's steering at constant speed: pure pursuit along the lane of the
    route, acceleration 0 (it never brakes); an ``EgoPlanner``.

    The base of a residual RL ego whose acceleration is its own
    (``base_planner="lane"`` in :mod:`policies.rl.envs`): its untrained policy keeps its
    lane and speed, and the policy learns when to brake, accelerate and leave the lane.
    Arguments as :class:`IDMPlanner`.
    """

    def __call__(self, observation: np.ndarray | None, view: SceneView) -> np.ndarray:
        """(2,) (0 [m/s^2], the IDM planner's yaw rate [rad/s]); zeros when the agent is not
        live. Only the steering is computed
        (:meth:`~riskflow_env.agents.idm.IDMPolicy.steer`), not the car following.
        """
        return np.array([0.0, self.policy.steer(view).get(self.agent, 0.0)])
