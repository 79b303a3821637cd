"""SCR and ORR on hand-made rollouts whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.metrics import (
    NO_EGO,
    collision_rates,
    collisions,
    offroad,
    offroad_counts,
    offroad_rates,
    rollout_metrics,
)
from tests.riskflow_env.metrics.records import record_of as record_against


def record_of(tracks, road=None, ego_index=0, num_context=0, **kwargs):
    """Every track against itself, ``tracks[ego_index]`` the ego's."""
    states = np.stack(tracks)
    kwargs.update(ego_index=ego_index, drivable_map=road, num_context=num_context)
    return record_against(states, states, **kwargs)


def rear_end(straight, steps=30):
    """Ego (slot 0) parked at x = 20; slot 1 from x = 0 at 10 m/s: boxes of length 4
    touch when the gap is 4 m, i.e. at x_1 = 16, step 16."""
    return [straight(20.0, 0.0, steps), straight(0.0, 10.0, steps)]


def test_forced_overlap_collides_with_the_ego_at_the_known_step(straight):
    result = collisions(record_of(rear_end(straight)))
    assert result.collided and result.ego_collided
    assert result.first_step == 16  # touching counts, as in the env
    assert result.pairs[0, 1] and result.pairs[1, 0] and not result.pairs[0, 0]


def test_context_steps_and_invalid_agents_are_not_counted(straight):
    assert collisions(record_of(rear_end(straight), num_context=17)).first_step == 17
    valid = np.ones((2, 30), bool)
    valid[1, 10:] = False  # slot 1 leaves the scene before reaching the ego
    assert not collisions(record_of(rear_end(straight), valid=valid)).collided


def test_collision_without_the_ego_and_scr_over_rollouts(straight):
    ego_far = straight(-100.0, 0.0, 30)
    others = record_of([ego_far, *rear_end(straight)])
    assert collisions(others).collided and not collisions(others).ego_collided
    no_ego = record_of(rear_end(straight), ego_index=NO_EGO)
    assert collisions(no_ego).collided and not collisions(no_ego).ego_collided
    apart = record_of([straight(0.0, 10.0, 30), straight(0.0, 10.0, 30, y=4.0)])
    assert not collisions(apart).collided and collisions(apart).first_step == -1
    results = [collisions(r) for r in (record_of(rear_end(straight)), others, apart)]
    assert collision_rates(results) == pytest.approx((2 / 3, 1 / 3))
    assert np.isnan(collision_rates([])[0])


def test_vehicle_leaving_a_box_road_gives_the_known_orr(road, straight):
    # Centre at x_t = 10.5 + t m (10 m/s, dt 0.1): off the road (x > 50) from t = 40;
    # the front midpoint (x + 2) from t = 38. 60 steps in all.
    leaving = straight(10.5, 10.0, 60)
    result = offroad(record_of([leaving], road))
    assert (result.centroid_steps, result.footprint_steps, result.agent_steps) == (20, 22, 60)
    assert result.centroid_rate == pytest.approx(1 / 3)
    assert result.footprint_rate == pytest.approx(22 / 60)


def test_orr_pools_agent_steps_and_respects_evaluated(road, straight):
    leaving, staying = straight(10.5, 10.0, 60), straight(10.5, 0.0, 60)
    both = record_of([leaving, staying], road)
    assert offroad(both).centroid_rate == pytest.approx(20 / 120)
    only_leaving = record_of([leaving, staying], road, evaluated=np.array([True, False]))
    assert offroad(only_leaving).centroid_rate == pytest.approx(20 / 60)
    pooled = offroad_rates([offroad(both), offroad(record_of([staying], road))])
    assert pooled == pytest.approx((20 / 180, 22 / 180))
    # Context steps are not counted: 10 context steps leave 50 scored, still 20 off.
    assert offroad(record_of([leaving], road, num_context=10)).centroid_rate == pytest.approx(0.4)


def test_orr_needs_a_map(straight):
    with pytest.raises(ValueError, match="drivable_map"):
        offroad(record_of([straight(0.0, 1.0, 5)]))
    assert rollout_metrics(record_of([straight(0.0, 1.0, 5)]))["agent_steps"] == 0.0


def test_offroad_counts_counts_flags_inside_the_mask_only():
    centroid = np.array([[True, False, True], [False, False, True]])
    footprint = np.array([[True, True, True], [False, True, True]])
    counted = np.array([[True, True, False], [True, True, True]])
    result = offroad_counts(centroid, footprint, counted)
    assert (result.centroid_steps, result.footprint_steps, result.agent_steps) == (2, 4, 5)
    assert np.isnan(offroad_counts(centroid, footprint, np.zeros_like(counted)).centroid_rate)
    with pytest.raises(ValueError, match="one shape"):
        offroad_counts(centroid, footprint, counted[:, :2])
