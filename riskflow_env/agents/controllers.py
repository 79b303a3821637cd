"""Shared driving primitives for scene policies, vectorised over agents.

* :func:`pure_pursuit` — yaw rate that steers a unicycle toward a lookahead point;
  :func:`arc_frame` — points in a vehicle's frame bent along its steering arc.
* :func:`speed_control` — proportional speed tracking.
* :func:`idm_acceleration` — the Intelligent Driver Model (Treiber, Hennecke and
  Helbing, "Congested traffic states in empirical observations and microscopic
  simulations", Phys. Rev. E 62, 1805, 2000).

Lane matching and lookups along lanes live in :mod:`riskflow_env.agents.lane_graph`. All arrays
are numpy; ``N`` is the number of agents queried.
"""

from __future__ import annotations

import numpy as np

from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, YAW
from riskflow_env.geometry import to_frame


def pure_pursuit(
    state: np.ndarray, target: np.ndarray, config: DynamicsConfig | None = None
) -> np.ndarray:
    """Yaw rate that puts a unicycle on the circular arc through a target point.

    curvature = 2 * lateral / distance^2 (target in the vehicle frame), yaw rate =
    speed * curvature, clipped to ``[-yaw_rate_max, yaw_rate_max]``.

    Args:
        state: (N, 4) (x [m], y [m], v [m/s], psi [rad]).
        target: (N, 2) [m] lookahead points.
        config: dynamics bounds (``yaw_rate_max`` [rad/s]); defaults when None.

    Returns:
        (N,) [rad/s].
    """
    config = config or DynamicsConfig()
    curvature = arc_curvature(state, target)
    return np.clip(state[:, SPEED] * curvature, -config.yaw_rate_max, config.yaw_rate_max)


def arc_curvature(state: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N,) [1/m] curvature (positive left) of the arc from each vehicle through its target.

    Args:
        state: (N, 4) (x [m], y [m], v [m/s], psi [rad]); target: (N, 2) [m].
    """
    rel = target - state[:, :2]
    _, lateral = to_frame(rel[:, 0], rel[:, 1], np.cos(state[:, YAW]), np.sin(state[:, YAW]))
    return 2.0 * lateral / np.maximum(np.sum(rel * rel, axis=-1), 1e-6)


def arc_frame(
    dx: np.ndarray, dy: np.ndarray, curvature: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points in a vehicle's frame -> coordinates along the arc of ``curvature``.

    Args:
        dx, dy: (...) [m] points ahead (x) and to the left (y) of the vehicle.
        curvature: (...) [1/m] signed, positive turning left; |k| < 1e-4 is straight.

    Returns:
        along: (...) [m] arclength to the point's projection on the arc (in
        (-pi R, pi R]); lateral: (...) [m] offset from the arc, positive left;
        turned: (...) [rad] heading change of the arc up to that point.
    """
    straight = np.abs(curvature) < 1e-4
    k = np.where(straight, 1.0, curvature)
    radius = 1.0 / np.abs(k)
    sign = np.sign(k)
    angle = np.arctan2(dx, radius - sign * dy)
    along = np.where(straight, dx, radius * angle)
    lateral = np.where(straight, dy, sign * (radius - np.hypot(dx, dy - 1.0 / k)))
    turned = np.where(straight, 0.0, sign * angle)
    return along, lateral, turned


def speed_control(speed: np.ndarray, target: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """(N,) [m/s^2] proportional acceleration ``gain * (target - speed)``.

    Args:
        speed, target: (N,) [m/s]; gain: [1/s].
    """
    return gain * (np.asarray(target) - np.asarray(speed))


def idm_acceleration(
    speed: np.ndarray,
    desired_speed: np.ndarray,
    gap: np.ndarray,
    closing_speed: np.ndarray,
    *,
    accel_max: float,
    decel_comfort: float,
    time_headway: float,
    min_gap: float,
    delta: float = 4.0,
) -> np.ndarray:
    """Intelligent Driver Model acceleration (Treiber et al. 2000).

    ``a = a_max * (1 - (v / v0)^delta - (s* / s)^2)`` with the desired gap
    ``s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b)))``.

    Args:
        speed: (N,) v [m/s].
        desired_speed: (N,) v0 [m/s], > 0.
        gap: (N,) s [m] bumper-to-bumper gap to the leader, ``inf`` when there is none
            (floored at 1 cm).
        closing_speed: (N,) dv = v - v_leader [m/s] (positive when approaching).
        accel_max: a_max [m/s^2]; decel_comfort: b [m/s^2], > 0.
        time_headway: T [s]; min_gap: s0 [m]; delta: free-road exponent [-].

    Returns:
        (N,) [m/s^2], unbounded below (clip to the dynamics bounds).
    """
    speed = np.asarray(speed, dtype=np.float64)
    brake = speed * closing_speed / (2.0 * np.sqrt(accel_max * decel_comfort))
    desired_gap = min_gap + np.maximum(0.0, speed * time_headway + brake)
    interaction = (desired_gap / np.maximum(gap, 1e-2)) ** 2
    free_road = (speed / desired_speed) ** delta
    return accel_max * (1.0 - free_road - interaction)
