"""Per-step rewards, broken out by term (the sum is what the env returns)."""

from __future__ import annotations

import numpy as np

from riskflow_env.config import DynamicsConfig, RewardConfig
from riskflow_env.events import FrameEvents
from riskflow_env.state import SceneState

REWARD_TERMS = ("speed", "collision", "offroad", "risk", "comfort")


def reward_terms(
    state: SceneState,
    events: FrameEvents,
    risk: np.ndarray,
    config: RewardConfig,
    dynamics: DynamicsConfig,
) -> dict[str, np.ndarray]:
    """Weighted reward terms of every slot (see :class:`RewardConfig` for the formula).

    Args:
        state: the state after the step.
        events: collisions and off-road flags of that state.
        risk: (A, A) TTC risk weights, zero on masked pairs.
        config: reward weights.
        dynamics: bounds used to normalise the comfort term.

    Returns:
        term name -> (A,) float64.
    """
    speed = state.current[:, 2]
    accel, yaw_rate = state.last_action[:, 0], state.last_action[:, 1]
    accel_scale = np.where(accel >= 0, dynamics.accel_max, -dynamics.accel_min)
    return {
        "speed": config.speed * np.minimum(speed, config.target_speed) / config.target_speed,
        "collision": config.collision * events.collided,
        "offroad": config.offroad * events.offroad,
        "risk": config.risk * risk.max(axis=-1, initial=0.0),
        "comfort": config.comfort
        * ((accel / accel_scale) ** 2 + (yaw_rate / dynamics.yaw_rate_max) ** 2),
    }
