"""Ego planners to stress-test: callables ``planner(observation, view) -> action``.

* :class:`IDMPlanner` — IDM lane following that reacts to the vehicles ahead
  (:class:`~riskflow_env.agents.idm.IDMPolicy` restricted to the ego);
* :class:`LaneKeepingPlanner` — the IDM planner's steering at constant speed;
* :class:`SamplingMPCPlanner` — sampling MPC against constant-velocity predictions of the
  other vehicles (evades; far fewer collisions than IDM under the adversary);
* :class:`OraclePlanner` — the same MPC reading the adversary's plans (privileged: a
  reference for what is avoidable, not a planner to deploy);
* :class:`ConstantVelocityPlanner` — keeps speed and heading.

Any function with the :class:`EgoPlanner` signature is a planner too
(``examples/stress_test_planner.py`` shows one).
"""

from __future__ import annotations

from policies.planners.base import EgoPlanner, as_action, reset_planner
from policies.planners.constant_velocity import ConstantVelocityPlanner
from policies.planners.idm_planner import IDMPlanner, LaneKeepingPlanner
from policies.planners.sampling_mpc import OraclePlanner, SamplingMPCPlanner

PLANNERS = {
    "idm": IDMPlanner,
    "lane_keeping": LaneKeepingPlanner,
    "sampling_mpc": SamplingMPCPlanner,
    "constant_velocity": ConstantVelocityPlanner,
}

__all__ = [
    "PLANNERS",
    "ConstantVelocityPlanner",
    "EgoPlanner",
    "IDMPlanner",
    "LaneKeepingPlanner",
    "OraclePlanner",
    "SamplingMPCPlanner",
    "as_action",
    "reset_planner",
]
