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
    loaded,
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


def comb(teeth: int, height: float, shift: float = 0.0) -> np.ndarray:
    """A comb-shaped polygon (2 teeth + 2, 2) [m]: ``teeth`` spikes ``height`` m tall on
    x in [shift, shift + 100]."""
    x = np.linspace(0.0, 100.0, 2 * teeth) + shift
    top = np.where(np.arange(2 * teeth) % 2 == 0, height, 0.5)
    return np.concatenate([np.stack([x, top], axis=1), [[100.0 + shift, 0.0], [shift, 0.0]]])


def test_polygons_piled_on_one_spot_refused_by_their_row_crossings(tmp_path):
    """50 comb-shaped lane polygons of 10,000 vertices on one spot: testing which meet
    took 3.9 s and their union 8.8 s. Their outlines cross 40 M pixel rows (the nuScenes
    samples 12,000-31,000): refused by MAX_FILL_CROSSINGS before any crossing is computed."""
    shared = comb(5_000, 40.0)  # one array: pickled once
    lanes = {f"c{i}": lane_feature([[10.0, 1.0], [90.0, 1.0]], polygon=shared) for i in range(50)}
    path = scene_file(tmp_path, "combs.pkl", scene_description(features=lanes))
    refused(run(path, "load_scenarionet"), "combs.pkl", "MAX_FILL_CROSSINGS")


def test_crossing_zigzag_polygons_load_without_a_union(tmp_path):
    """10 combs crossing 10 others at right angles, 3 M crossings of their outlines: their
    union took 12 s of CPU and 500 MB (the same at 400 teeth: 49 s)."""
    lanes = {}
    for i in range(10):
        upright = comb(200, 100.0, 0.37 * i)
        lanes[f"h{i}"] = lane_feature([[10.0, 1.0], [90.0, 1.0]], polygon=upright)
        lanes[f"v{i}"] = lane_feature(
            [[99.0, 10.0], [99.0, 90.0]], polygon=np.stack([100 - upright[:, 1], upright[:, 0]], 1)
        )
    path = scene_file(tmp_path, "zigzags.pkl", scene_description(features=lanes))
    loaded(run(path, "load_scenarionet", ", crop=False"))
