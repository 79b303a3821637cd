"""Three straight one-road scenes with their own maps, agent counts and headings, for
tests that batch scenes (batched planning, the vector env)."""

from __future__ import annotations

import numpy as np

from riskflow_env.maps import Lane, from_lanes
from riskflow_env.scenarios import Scenario

# (road centreline end points, road width [m], starts (s, d) in the road frame, speed [m/s])
ROADS = [
    (((-150.0, 0.0), (500.0, 0.0)), 12.0, [(0, 0), (18, 3.5), (-12, -3.5), (9, 0.5)], 12.0),
    (((-100.0, -80.0), (400.0, 220.0)), 8.0, [(0, 0), (14, 2.5), (-9, -2.5), (25, 0), (6, -3)],
     9.0),
    (((-200.0, 40.0), (300.0, 40.0)), 10.0, [(0, 0), (10, 0.2), (-15, 3), (22, -3), (35, 3),
                                            (-30, -3), (5, 4.2)], 14.0),
]  # fmt: skip


def make_scenario(index: int) -> Scenario:
    """Scene ``index`` of :data:`ROADS`: its agents drive straight along the road at its
    speed, 31 history + 60 future steps."""
    (start, end), width, starts, speed = ROADS[index]
    start, end = np.array(start), np.array(end)
    road = from_lanes([Lane(np.stack([start, end]), width, f"road{index}")])
    heading = np.arctan2(*(end - start)[::-1])
    along = (end - start) / np.linalg.norm(end - start)
    left = np.array([-along[1], along[0]])
    steps = 31 + 60
    time = 0.1 * (np.arange(steps) - 30)
    states = np.zeros((len(starts), steps, 4))
    for row, (s, d) in enumerate(starts):
        centre = start + 150.0 * along + s * along + d * left
        states[row, :, :2] = centre + (speed * time)[:, None] * along
        states[row, :, 2], states[row, :, 3] = speed, heading
    valid = np.ones(states.shape[:2], dtype=bool)
    num = len(starts)
    return Scenario(road, states, valid, np.full(num, 4.5), np.full(num, 2.0), name=f"s{index}")
