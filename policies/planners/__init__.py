"""Ego planners to stress-test: callables ``planner(observation, view) -> action``.

* :class:`IDMPlanner` — IDM lane following that reacts to the vehicles ahead
  (:class:`~riskflow_env.agents.idm.IDMPolicy` restricted to the ego);
* :class:`LaneKeepingPlanner` — the IDM planner's steering at constant speed;
* :class:`SamplingMPCPlanner` — sampling MPC against constant-velocity predictions of the
  other vehicles (evades; far fewer collisions than IDM under the adversary);
* :class:`OraclePlanner` — the same MPC reading the adversary's plans (privileged: a
  reference for what is avoidable, not a planner to deploy);
* :class:`ConstantVelocityPlanner` — keeps speed and heading;
* :class:`ReplayPlanner` — the ego replays its logged future (a reference, not a planner
  that reacts).

:data:`PLANNERS` names each (the names ``riskflow-eval --ego``, the examples and the RL
reports use); :func:`make_planner` builds one.

Any function with the :class:`EgoPlanner` signature is a planner too
(``examples/stress_test_planner.py`` shows one).
"""

from __future__ import annotations

import inspect

from policies.planners.base import EgoPlanner, as_action, reset_planner
from policies.planners.constant_velocity import ConstantVelocityPlanner
from policies.planners.idm_planner import IDMPlanner, LaneKeepingPlanner
from policies.planners.replay import ReplayPlanner
from policies.planners.sampling_mpc import OraclePlanner, SamplingMPCPlanner
from riskflow_env.config import DynamicsConfig

PLANNERS: dict[str, type] = {
    "idm": IDMPlanner,
    "lane_keeping": LaneKeepingPlanner,
    "sampling_mpc": SamplingMPCPlanner,
    "constant_velocity": ConstantVelocityPlanner,
    "replay": ReplayPlanner,
}


def make_planner(name: str, dynamics: DynamicsConfig | None = None) -> EgoPlanner:
    """A fresh planner ``name`` (one of :data:`PLANNERS`); ``dynamics`` (the env's
    bounds) goes to the planners that take it."""
    if name not in PLANNERS:
        raise ValueError(f"planner must be one of {tuple(PLANNERS)}, got {name!r}")
    planner = PLANNERS[name]
    if dynamics is not None and "dynamics" in inspect.signature(planner).parameters:
        return planner(dynamics=dynamics)
    return planner()


__all__ = [
    "PLANNERS",
    "ConstantVelocityPlanner",
    "EgoPlanner",
    "IDMPlanner",
    "LaneKeepingPlanner",
    "OraclePlanner",
    "ReplayPlanner",
    "SamplingMPCPlanner",
    "as_action",
    "make_planner",
    "reset_planner",
]
