"""Hand-made constant-velocity scenes on a box road and their env, for the event-log and
render tests (the event-log tests' subprocesses import it too)."""

from __future__ import annotations

import numpy as np
import shapely

import riskflow_env
from riskflow_env.config import EnvConfig
from riskflow_env.maps import from_polygons
from riskflow_env.scenarios import Scenario

ROAD = shapely.box(-50.0, -12.0, 250.0, 12.0)


def make_scenario(vehicles, road=ROAD, steps: int = 60, name: str = "hand-made") -> Scenario:
    """Constant-velocity tracks for ``vehicles`` rows (x, y, v, yaw), the ego first."""
    rows = np.asarray(vehicles, dtype=np.float64)
    t = np.arange(-30, steps + 1) * 0.1
    x = rows[:, None, 0] + rows[:, None, 2] * np.cos(rows[:, None, 3]) * t
    y = rows[:, None, 1] + rows[:, None, 2] * np.sin(rows[:, None, 3]) * t
    speed, yaw = (
        np.broadcast_to(rows[:, None, 2], x.shape),
        np.broadcast_to(rows[:, None, 3], x.shape),
    )
    return Scenario(
        map=from_polygons(road, resolution=0.5),
        states=np.stack([x, y, speed, yaw], axis=-1),
        valid=np.ones(x.shape, dtype=bool),
        length=np.full(len(rows), 4.5),
        width=np.full(len(rows), 2.0),
        name=name,
    )


def make_env(
    vehicles,
    steps: int = 30,
    road=ROAD,
    render_mode: str | None = None,
    scenario_steps: int = 60,
    name: str = "hand-made",
):
    """The env of :func:`make_scenario` (``scenario_steps`` future steps): ``steps`` steps
    an episode, no termination, every vehicle kept to the end."""
    config = EnvConfig(
        max_agents=len(vehicles),
        episode_steps=steps,
        terminate_on_collision="none",
        terminate_on_offroad="none",
        end_with_ego=False,
    )
    scenario = make_scenario(vehicles, road, scenario_steps, name)
    return riskflow_env.parallel_env(config=config, scenarios=scenario, render_mode=render_mode)
