"""Shared builders of hand-made rollouts for the metric tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from shapely.geometry import box

from riskflow_env import dynamics
from riskflow_env.config import DynamicsConfig
from riskflow_env.maps import DrivableMap, from_polygons

ROAD_X = (0.0, 50.0)  # [m] the box road's extent along x
ROAD_HALF_WIDTH = 5.0  # [m]


@pytest.fixture(scope="session")
def road() -> DrivableMap:
    """A 50 m x 10 m box road: x in [0, 50], y in [-5, 5]."""
    return from_polygons([box(ROAD_X[0], -ROAD_HALF_WIDTH, ROAD_X[1], ROAD_HALF_WIDTH)])


def _straight(x0: float, speed: float, steps: int, y: float = 0.0, dt: float = 0.1) -> np.ndarray:
    """(T, 4) constant-speed track along +x from (x0, y)."""
    track = np.zeros((steps, 4))
    track[:, 0] = x0 + speed * dt * np.arange(steps)
    track[:, 1] = y
    track[:, 2] = speed
    return track


def _rolled(initial: np.ndarray, actions: np.ndarray, dt: float = 0.1) -> np.ndarray:
    """(T + 1, 4) unicycle rollout of ``actions`` (T, 2) from ``initial`` (4,), with it."""
    config = DynamicsConfig(dt=dt, accel_min=-20.0, accel_max=20.0, yaw_rate_max=3.0)
    after = dynamics.rollout(np.asarray(initial, float), np.asarray(actions, float), config)
    return np.concatenate([np.asarray(initial, float)[None], after])


@pytest.fixture
def straight() -> Callable[..., np.ndarray]:
    """``straight(x0, speed, steps, y=0, dt=0.1)`` -> (T, 4) constant-speed track."""
    return _straight


@pytest.fixture
def rolled() -> Callable[..., np.ndarray]:
    """``rolled(initial (4,), actions (T, 2), dt=0.1)`` -> (T + 1, 4) unicycle track."""
    return _rolled
