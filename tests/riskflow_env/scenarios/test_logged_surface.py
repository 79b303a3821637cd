"""The ground under the logged vehicles is drivable (riskflow_env.scenarios.logged_surface)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from riskflow_env.metrics.safety import footprint_sdf
from riskflow_env.scenarios import logged_surface as surface
from riskflow_env.scenarios.scenarionet import load_scenarionet, scenario_from_description
from tests.riskflow_env.scenarios.scenarionet_sources import description
from tests.samples import require_samples

PARKED = (-60.0, 6.5)  # [m] beside the toy road (edges at y = +-3.5 m), no lot drawn


def _with_parked_car(source: str) -> dict:
    """The toy description of ``source`` plus a car parked at :data:`PARKED`, beside
    the road where the map data draws nothing."""
    scene = copy.deepcopy(description(source))
    steps = len(scene["metadata"]["ts"])
    state = copy.deepcopy(scene["tracks"]["car"]["state"])
    state["position"] = np.tile([PARKED[0], PARKED[1], 0.0], (steps, 1))
    state["heading"] = np.zeros(steps)
    state["velocity"] = np.zeros((steps, 2))
    state["valid"] = np.ones(steps)
    scene["tracks"]["parked"] = {"type": "VEHICLE", "state": state, "metadata": {}}
    return scene


def test_a_parked_car_beside_the_drawn_road_stands_on_the_map_and_its_neighbourhood_does_not():
    scenario = scenario_from_description(_with_parked_car("argoverse2"))
    row = scenario.agent_ids.index("parked")
    sdf = footprint_sdf(scenario.map, scenario.states[row : row + 1], *(
        a[row : row + 1] for a in (scenario.length, scenario.width)
    ))  # fmt: skip
    assert np.all(sdf[0, scenario.valid[row]] < 0)  # every footprint point, every step
    beside = np.array([[PARKED[0] + 6.0, PARKED[1]], [PARKED[0] - 6.0, PARKED[1]]])
    assert np.all(scenario.map.sdf_at(beside) > 0)  # the rest of the undrawn area stays off


def test_a_parked_track_is_two_boxes_and_a_moving_one_a_box_about_every_metre():
    steps = 50
    parked = np.zeros((steps, 2))
    moving = np.stack([0.5 * np.arange(steps), np.zeros(steps)], axis=1)  # 0.5 m a step
    xy = np.stack([parked, moving])
    kept = surface._kept_steps(xy, np.zeros((2, steps)), np.ones((2, steps), dtype=bool))
    assert np.flatnonzero(kept[0]).tolist() == [0, steps - 1]
    assert kept[1].sum() == pytest.approx(0.5 * steps / surface.SPACING, abs=2)


def test_a_gap_in_a_track_keeps_the_boxes_on_both_sides_of_it():
    steps = 20
    valid = np.ones((1, steps), dtype=bool)
    valid[0, 8:12] = False
    kept = surface._kept_steps(np.zeros((1, steps, 2)), np.zeros((1, steps)), valid)
    assert np.flatnonzero(kept[0]).tolist() == [0, 7, 12, 19]


def test_over_max_boxes_the_boxes_are_thinned_by_a_stride(monkeypatch):
    steps = 400
    xy = np.stack([np.arange(steps) * 2.0, np.zeros(steps)], axis=1)[None]  # 2 m a step
    heading, valid = np.zeros((1, steps)), np.ones((1, steps), dtype=bool)
    assert len(surface.box_steps(xy, heading, valid)[0]) == steps
    monkeypatch.setattr(surface, "MAX_BOXES", 100)
    rows, kept = surface.box_steps(xy, heading, valid)
    assert len(rows) == 100 and kept.tolist() == list(range(0, steps, 4))
    assert not surface.logged_boxes(xy, heading, ~valid, np.ones(1), np.ones(1)).xy.size


def test_logged_vehicles_stand_on_the_map_at_every_step_of_the_nuscenes_samples():
    """scene-0655's car park is not in the map data (28 parked cars stood 'off road' at
    the first step); with the logged surface every logged footprint is on the map."""
    for path in require_samples():
        scenario = load_scenarionet(path)
        sdf = footprint_sdf(scenario.map, scenario.states, scenario.length, scenario.width)
        on_map = (sdf <= 0).all(axis=-1)[scenario.valid]
        assert on_map.mean() >= 0.99, (path.name, on_map.mean())
