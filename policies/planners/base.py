"""The ``EgoPlanner`` protocol: the planner under test, driving the ego.

An ego planner is any callable ``planner(observation, view) -> action``:

* ``observation``: the ego's observation vector of ``riskflow_v0`` (``(D,)`` float32,
  layout in :mod:`riskflow_env.observations`: own state, the nearest neighbours in the
  ego's frame, map SDF rays);
* ``view``: the read-only :class:`~riskflow_env.view.SceneView` of the whole scene (map
  and lanes, every vehicle's history, the scenario), for planners that need more than
  the observation;
* ``action``: ``(2,)`` (acceleration [m/s^2], yaw rate [rad/s]); the env clips it to the
  dynamics bounds (``EnvConfig.clip_actions``) and rejects NaN.

A plain function is a planner. A planner with state may also have ``reset(view)``,
called at the start of every episode (:func:`reset_planner`).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from riskflow_env.view import SceneView


@runtime_checkable
class EgoPlanner(Protocol):
    """``planner(observation (D,), view) -> (accel [m/s^2], yaw_rate [rad/s])``."""

    def __call__(self, observation: np.ndarray, view: SceneView) -> np.ndarray:
        """The ego's action for this step."""
        ...


def reset_planner(planner: EgoPlanner, view: SceneView) -> None:
    """Call ``planner.reset(view)`` when the planner has one (plain functions do not)."""
    reset = getattr(planner, "reset", None)
    if callable(reset):
        reset(view)


def as_action(action: object, name: str = "planner") -> np.ndarray:
    """``action`` as a (2,) float64 array; ValueError naming ``name`` if it is not one."""
    try:
        array = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must return an action of two numbers (accel [m/s^2], yaw rate "
            f"[rad/s]), got {action!r:.60}"
        ) from None
    if array.shape != (2,):
        raise ValueError(
            f"{name} must return an action of shape (2,) (accel [m/s^2], yaw rate [rad/s]), "
            f"got shape {array.shape}"
        )
    return array
