"""Frozen, validated configuration dataclasses. Every field carries its unit."""

from __future__ import annotations

import math
from dataclasses import dataclass


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _finite(name: str, value: float) -> None:
    _require(
        isinstance(value, (int, float)) and math.isfinite(value),
        f"{name} must be a finite number, got {value!r}",
    )


@dataclass(frozen=True)
class DynamicsConfig:
    """Unicycle model bounds and time step (DESIGN.md section 4).

    Attributes:
        dt: integration step [s].
        accel_min: strongest braking allowed [m/s^2] (negative).
        accel_max: strongest acceleration allowed [m/s^2].
        yaw_rate_max: bound on |yaw rate| [rad/s].
        speed_min: lowest speed [m/s]; 0 means vehicles never reverse.
        speed_max: highest speed [m/s].
    """

    dt: float = 0.1
    accel_min: float = -8.0
    accel_max: float = 5.0
    yaw_rate_max: float = 1.0
    speed_min: float = 0.0
    speed_max: float = 40.0

    def __post_init__(self) -> None:
        for name in ("dt", "accel_min", "accel_max", "yaw_rate_max", "speed_min", "speed_max"):
            _finite(f"DynamicsConfig.{name}", getattr(self, name))
        _require(self.dt > 0, f"DynamicsConfig.dt must be > 0 s, got {self.dt}")
        _require(
            self.accel_min < 0 < self.accel_max,
            "DynamicsConfig needs accel_min < 0 < accel_max [m/s^2], "
            f"got accel_min={self.accel_min}, accel_max={self.accel_max}",
        )
        _require(
            self.yaw_rate_max > 0,
            f"DynamicsConfig.yaw_rate_max must be > 0 rad/s, got {self.yaw_rate_max}",
        )
        _require(
            0 <= self.speed_min < self.speed_max,
            "DynamicsConfig needs 0 <= speed_min < speed_max [m/s], "
            f"got speed_min={self.speed_min}, speed_max={self.speed_max}",
        )
