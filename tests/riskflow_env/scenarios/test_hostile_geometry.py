"""Hostile ScenarioNet geometry: lane graphs and polygons whose cost grows
faster than their size are refused, or loaded, within a CPU-time bound and 500 MB.

Every file is built here and read by ``load_scenarionet`` in a child process whose
address space is capped at 1.5 GB (:mod:`tests.capped`).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.riskflow_env.scenarios.hostile_files import (
    lane_feature,
    refused,
    run,
    scene_description,
    scene_file,
)

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

WIDTH = np.array([2.0, 2.0])  # [m]


def test_lanes_meeting_at_one_point_refused_by_their_links(tmp_path):
    """2,500 lanes ending where 2,500 others start: 64 successors each, 160,000 junction
    patches piled on one point (14 s and 620 MB, then an allocation failure)."""
    angle = np.linspace(0.0, np.pi / 2, 5000)
    x, y = 50 + 30 * np.cos(angle), 10 + 30 * np.sin(angle)
    lanes = {
        f"in{i}": lane_feature([[x[i], y[i]], [50, 10]], width=WIDTH) for i in range(0, 5000, 2)
    }
    lanes |= {
        f"out{i}": lane_feature([[50, 10], [100 - x[i], 20 - y[i]]], width=WIDTH)
        for i in range(1, 5000, 2)
    }
    path = scene_file(tmp_path, "fan.pkl", scene_description(features=lanes))
    refused(run(path, "load_scenarionet", ", crop=False"), "fan.pkl", "MAX_LANE_LINKS")


def test_listed_exit_lanes_past_the_link_limit_refused(tmp_path):
    lanes = {
        f"l{i}": lane_feature(
            [[-40.0 + i % 20, 10.0 * (i // 20)], [-39.0 + i % 20, 10.0 * (i // 20)]],
            exit_lanes=[f"l{(i + k) % 400}" for k in range(1, 65)],
        )
        for i in range(400)
    }
    path = scene_file(tmp_path, "exits.pkl", scene_description(features=lanes))
    refused(run(path, "load_scenarionet", ", crop=False"), "exits.pkl", "MAX_LANE_LINKS")


def test_polygons_piled_on_one_spot_refused_before_their_union(tmp_path):
    """50 comb-shaped lane polygons of 10,000 vertices on one spot (one array, shared):
    testing which meet took 3.9 s and their union 8.8 s; refused from their vertices
    (MAX_OVERLAP_WORK)."""
    x = np.linspace(0.0, 100.0, 10_000)
    top = np.where(np.arange(10_000) % 4 < 2, 40.0, -39.0)
    comb = np.concatenate([np.stack([x, top], axis=1), [[100.0, -40.0], [0.0, -40.0]]])
    lanes = {f"c{i}": lane_feature([[10.0, 1.0], [90.0, 1.0]], polygon=comb) for i in range(50)}
    path = scene_file(tmp_path, "combs.pkl", scene_description(features=lanes))
    refused(run(path, "load_scenarionet"), "combs.pkl", "MAX_OVERLAP_WORK")
