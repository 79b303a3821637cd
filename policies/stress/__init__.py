"""Stress-test an ego planner: find its failures, and keep only those that matter.

* :mod:`policies.stress.failures`: every ego collision classified (type, speeds, guided
  vehicles nearby), checked for avoidability by a hindsight escape search
  (:mod:`policies.stress.escape`) and its attacker held to human kinematic bounds;
* :mod:`policies.stress.summary`: the rates that rank planners, with 95% intervals;
* :func:`riskflow_stress` (``riskflow-stress``, :mod:`policies.stress.cli`): a planner
  against the adversary on many scenes and seeds, a report, a replay file per failure
  (:func:`replay` puts a planner back into it), :func:`compare` for two planners, paired.
"""

from policies.stress.compare import compare
from policies.stress.escape import CLEARANCE, Escape, EscapeSearch, Obstacles, find_escape
from policies.stress.failures import (
    FAILURE_TYPES,
    HUMAN_BOUNDS,
    Failure,
    KinematicBounds,
    analyse,
    collision_type,
    kinematic_bounds,
)
from policies.stress.planner_spec import PlannerSpecError, load_planner
from policies.stress.replay import load_replay, replay, save_replay
from policies.stress.stress_test import StressResult, riskflow_stress
from policies.stress.summary import Analysed, headline, stress_summary

__all__ = [
    "CLEARANCE",
    "FAILURE_TYPES",
    "HUMAN_BOUNDS",
    "Analysed",
    "Escape",
    "EscapeSearch",
    "Failure",
    "KinematicBounds",
    "Obstacles",
    "PlannerSpecError",
    "StressResult",
    "analyse",
    "collision_type",
    "compare",
    "find_escape",
    "headline",
    "kinematic_bounds",
    "load_planner",
    "load_replay",
    "replay",
    "riskflow_stress",
    "save_replay",
    "stress_summary",
]
