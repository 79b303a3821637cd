"""Stress-test an ego planner: find its failures, and keep only those that matter.

* :mod:`policies.stress.failures`: every ego collision classified (type, speeds, guided
  vehicles nearby), checked for avoidability by a hindsight escape search
  (:mod:`policies.stress.escape`) and its attacker held to human kinematic bounds;
* :mod:`policies.stress.summary`: the rates that rank planners, with 95% intervals.
"""

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
    "analyse",
    "collision_type",
    "find_escape",
    "headline",
    "kinematic_bounds",
    "stress_summary",
]
