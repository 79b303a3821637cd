"""Progress, stalls, parked cars turned in place and manoeuvres at the map's edge, on
hand-made rollouts whose right answers are known (riskflow_env.metrics.progress)."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.metrics import aggregate_rollout_metrics, progress, rollout_metrics
from riskflow_env.metrics.progress import EDGE_REACH, TURN_IN_PLACE
from tests.riskflow_env.metrics.records import record_of


def test_a_vehicle_that_stops_halfway_has_progress_one_half_and_is_stalled_below_it(straight):
    steps = 21  # 20 moves of 1 m in the log
    reference = np.stack([straight(0.0, 10.0, steps)] * 3)
    states = reference.copy()
    states[0, 11:, :2] = states[0, 10, :2]  # stops after 10 m
    states[1, 12:, :2] = states[1, 11, :2]  # stops after 11 m
    result = progress(record_of(states, reference))
    np.testing.assert_allclose(result.logged, 20.0)
    np.testing.assert_allclose(result.ratio, [0.5, 0.55, 1.0])
    assert result.mover.all() and result.stalled.tolist() == [False, False, False]
    states[0, 10:, :2] = states[0, 9, :2]  # stops after 9 m: 0.45 < 0.5
    assert progress(record_of(states, reference)).stalled.tolist() == [True, False, False]


def test_progress_counts_only_steps_where_the_log_is_valid_and_not_the_context(straight):
    reference = straight(0.0, 10.0, 11)[None]
    states = straight(0.0, 20.0, 11)[None]  # twice as far
    log_valid = np.ones((1, 11), dtype=bool)
    log_valid[0, 6:] = False  # the log ends after 5 moves
    result = progress(record_of(states, reference, log_valid, num_context=1))
    np.testing.assert_allclose(result.logged, [4.0])  # moves 1->2 .. 4->5
    np.testing.assert_allclose(result.ratio, [2.0])


def test_vehicles_that_barely_move_in_the_log_have_no_progress(straight):
    reference = straight(0.0, 1.0, 11)[None]  # 1 m in the log
    result = progress(record_of(reference.copy(), reference))
    assert not result.mover.any() and np.isnan(result.ratio).all()


def test_a_parked_car_spun_in_its_bay_is_turned_in_place_one_driven_away_is_not():
    steps = 10
    reference = np.zeros((3, steps, 4))
    reference[:, :, 0] = [[0.0], [20.0], [40.0]]
    states = reference.copy()
    states[0, 5:, 3] = TURN_IN_PLACE + 0.05  # spun in place
    states[1, 5:, 3] = TURN_IN_PLACE - 0.05  # turned a little
    states[2, 5:, 3] = 1.0  # turned and driven 5 m away
    states[2, 5:, 0] += 5.0
    result = progress(record_of(states, reference))
    assert result.parked.tolist() == [True, True, True]
    assert result.turned.tolist() == [True, False, False]


def test_hard_braking_heading_for_the_map_border_counts_the_same_braking_far_from_it_not(
    road, rolled
):
    """The box road's raster ends 5 m past x = 50 (the map margin)."""
    brake = np.tile([-6.0, 0.0], (15, 1))
    near = rolled([38.0, 0.0, 10.0, 0.0], brake)  # 17 m to the border, braking
    far = rolled([2.0, 0.0, 10.0, 0.0], brake)  # 53 m to it
    tracks = np.stack([near, far])
    steady = np.stack([rolled(t[0], np.zeros((15, 2))) for t in tracks])
    result = progress(record_of(tracks, steady, drivable_map=road))
    ahead = 55.0 - tracks[0, 1:, 0]
    expected = int(np.sum(ahead < EDGE_REACH))
    assert expected > 0
    assert result.edge_steps[0] == expected and result.edge_hard[0] == expected
    assert result.edge_hard[1] == 0  # the log drives on at constant speed
    assert result.edge_steps[1] > 0


def test_the_rollout_row_and_its_aggregate_pool_the_vehicles(straight):
    reference = np.stack([straight(0.0, 10.0, 21)] * 2)
    states = reference.copy()
    states[0, 6:, :2] = states[0, 5, :2]  # 5 m of 20: stalled
    row = rollout_metrics(record_of(states, reference))
    assert (row["movers"], row["stalled"]) == (2.0, 1.0)
    assert (row["driven_m"], row["logged_m"]) == pytest.approx((25.0, 40.0))
    merged = aggregate_rollout_metrics([row, row])
    assert merged["progress"] == pytest.approx(25.0 / 40.0)
    assert merged["stalled_share"] == pytest.approx(0.5)
    assert np.isnan(merged["turned_share"])  # no parked car
    old = {key: value for key, value in row.items() if key != "movers"}
    assert np.isnan(aggregate_rollout_metrics([old])["stalled_share"])  # a row before it
