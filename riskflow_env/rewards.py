"""Per-step rewards, broken out by term (the sum is what the env returns)."""

from __future__ import annotations

from riskflow_env._array import Array, namespace
from riskflow_env.config import DynamicsConfig, RewardConfig
from riskflow_env.events import FrameEvents
from riskflow_env.state import SceneState

REWARD_TERMS = ("speed", "collision", "offroad", "risk", "comfort")


def reward_terms(
    state: SceneState,
    events: FrameEvents,
    risk: Array,
    config: RewardConfig,
    dynamics: DynamicsConfig,
) -> dict[str, Array]:
    """Weighted reward terms of every slot (see :class:`RewardConfig` for the formula).

    Args:
        state: the state after the step (a :class:`SceneState`, or any object with
            ``current`` (..., A, 4) and ``last_action`` (..., A, 2) arrays: a batch).
        events: collisions and off-road flags of that state.
        risk: (..., A, A) TTC risk weights, zero on masked pairs.
        config: reward weights.
        dynamics: bounds used to normalise the comfort term.

    Returns:
        term name -> (..., A) float64 (the dtype of ``state.current``).
    """
    xp = namespace(risk)
    speed = state.current[..., 2]
    accel, yaw_rate = state.last_action[..., 0], state.last_action[..., 1]
    accel_scale = xp.where(accel >= 0, dynamics.accel_max, -dynamics.accel_min)
    return {
        "speed": config.speed * xp.minimum(speed, config.target_speed) / config.target_speed,
        "collision": config.collision * xp.astype(events.collided, speed.dtype),
        "offroad": config.offroad * xp.astype(events.offroad, speed.dtype),
        "risk": config.risk * _row_max(risk, xp),
        "comfort": config.comfort
        * ((accel / accel_scale) ** 2 + (yaw_rate / dynamics.yaw_rate_max) ** 2),
    }


def _row_max(risk: Array, xp) -> Array:
    """(..., A) max over the last axis, 0 for an empty last axis (risk is >= 0)."""
    if risk.shape[-1] == 0:
        return xp.zeros(risk.shape[:-1], dtype=risk.dtype)
    return xp.max(risk, axis=-1)
