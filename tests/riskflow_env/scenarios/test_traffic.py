"""Seeded synthetic traffic: on the road, no overlaps, plausible gaps, deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.geometry import footprint_points, pairwise_overlap
from riskflow_env.maps import FAMILIES
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig


@pytest.mark.parametrize("family", FAMILIES)
def test_placed_traffic_is_on_road_and_not_overlapping(family):
    source = HighwayTrafficSource(TrafficConfig(families=(family,), num_vehicles=(12, 12)))
    for seed in range(3):
        scenario = source.sample(np.random.default_rng(seed))
        now = scenario.states[:, scenario.current_index]
        assert scenario.num_agents >= 2
        assert not pairwise_overlap(now[:, :2], now[:, 3], scenario.length, scenario.width).any()
        points = footprint_points(now[:, :2], now[:, 3], scenario.length, scenario.width)
        assert np.all(scenario.map.sdf_at(points) <= 0.0)
        assert np.all(scenario.valid[:, scenario.current_index])
        speed_limit = max(lane.speed_limit or 20.0 for lane in scenario.map.lanes)
        assert np.all((now[:, 2] > 0) & (now[:, 2] <= speed_limit))


def test_history_moves_at_constant_speed_along_the_lane():
    scenario = HighwayTrafficSource(TrafficConfig(families=("highway",))).sample(
        np.random.default_rng(0)
    )
    states, valid = scenario.states, scenario.valid
    step = np.linalg.norm(np.diff(states[..., :2], axis=1), axis=-1)
    both = valid[:, 1:] & valid[:, :-1]
    np.testing.assert_allclose(step[both], (states[:, 1:, 2] * scenario.dt)[both], rtol=1e-6)


def test_same_generator_state_same_scenario():
    source = HighwayTrafficSource()
    a = source.sample(np.random.default_rng(5))
    b = source.sample(np.random.default_rng(5))
    assert a.name == b.name
    np.testing.assert_array_equal(a.states, b.states)


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="families"):
        TrafficConfig(families=("moon",))
    with pytest.raises(ValueError, match="num_vehicles"):
        TrafficConfig(num_vehicles=(5, 2))
