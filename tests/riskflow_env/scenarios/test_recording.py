"""Naturalistic traffic: highway-env recordings, validity masks, windows, fast stepping."""

from __future__ import annotations

import re

import numpy as np
import pytest

from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import inverse, rollout
from riskflow_env.geometry import footprint_points
from riskflow_env.maps import FAMILIES
from riskflow_env.scenarios import (
    DriverConfig,
    SceneConfig,
    cut_scenario,
    cut_scenarios,
    generate_scenario,
    record_traffic,
)
from riskflow_env.scenarios.road_stepper import MAX_YAW_RATE, RoadStepper

SPARSE = DriverConfig(extra_headway=(4.0, 4.0))  # few vehicles: fast tests
TINY = SceneConfig(future_steps=20, warmup=(5, 10), candidate_windows=2, driver=SPARSE)


@pytest.fixture(scope="module")
def merge_recording():
    return record_traffic("merge", np.random.default_rng(3), steps=120, warmup_steps=10)


def test_recorded_vehicles_lie_on_the_map(merge_recording):
    recording = merge_recording
    valid = recording.valid
    assert valid.sum() > 1000
    centre = recording.map.sdf_at(recording.states[..., :2][valid]) <= 0.0
    points = footprint_points(
        recording.states[..., :2],
        recording.states[..., 3],
        recording.length[:, None],
        recording.width[:, None],
    )
    footprint = np.all(recording.map.sdf_at(points) <= 0.0, axis=-1)[valid]
    assert centre.mean() >= 0.95 and footprint.mean() >= 0.95


def test_masks_follow_vehicles_entering_and_leaving(merge_recording):
    valid = merge_recording.valid
    first = np.argmax(valid, axis=1)
    last = valid.shape[1] - 1 - np.argmax(valid[:, ::-1], axis=1)
    assert np.all(valid.sum(axis=1) == last - first + 1)  # one contiguous run each
    assert np.any(first > 0), "some vehicles enter during the recording"
    assert np.any(last < valid.shape[1] - 1), "some vehicles leave during the recording"
    assert np.all(merge_recording.states[~valid] == 0.0)
    assert np.all(np.isfinite(merge_recording.states))


def test_recorded_motion_is_plausible(merge_recording):
    states, valid = merge_recording.states, merge_recording.valid
    both = valid[:, 1:] & valid[:, :-1]
    assert np.all(states[..., 2][valid] >= 0.0)  # no reversing
    yaw_rate = np.diff(states[..., 3], axis=1)[both] / merge_recording.dt
    assert np.abs(yaw_rate).max() <= MAX_YAW_RATE + 1e-6
    step = np.linalg.norm(np.diff(states[..., :2], axis=1), axis=-1)[both]
    assert step.max() <= 40.0 * merge_recording.dt  # no teleporting rows
    driver = DriverConfig()
    cars = np.array(merge_recording.kinds) == "car"
    assert np.all(merge_recording.length[cars] >= driver.car_length[0])
    assert np.all(merge_recording.length[cars] <= driver.car_length[1])


@pytest.mark.parametrize("family", ["roundabout", "racetrack"])
def test_recorded_tracks_reproduce_themselves_through_the_unicycle(family):
    """Vehicles move as the simulator's unicycle (heading = direction of travel; without
    the turning radius, as the shipped banks were recorded), so the logged actions, rolled
    out from a logged state, give back the logged positions: training targets that the
    generator can match. (Recorded with highway-env's bicycle, these missed by up to 2 m
    over 5 s on curved roads.)"""
    recording = record_traffic(family, np.random.default_rng(5), steps=60, warmup_steps=10)
    rows = recording.valid.all(axis=1)
    assert rows.sum() >= 3
    states = recording.states[rows]
    plain = DynamicsConfig(turn_radius_min=0.0)
    actions = inverse(states, plain)
    assert np.all(np.abs(actions[..., 1]) <= MAX_YAW_RATE + 1e-9)
    rolled = rollout(states[:, 0], actions, plain)
    # float64 arithmetic of the same formulas in a different order: 1e-6 m over 6 s.
    np.testing.assert_allclose(rolled[..., :2], states[:, 1:, :2], atol=1e-6)


def test_stopping_vehicles_stand_for_their_drawn_time():
    """``stop_share``: vehicles stop once in their lane and stand for the drawn time
    (braking not counted); without stops no highway vehicle stands."""
    driver = DriverConfig(stop_share=1.0, stop_start=(1.0, 2.0), stop_duration=(4.0, 4.0))
    recording = record_traffic("highway", np.random.default_rng(0), 160, 5, driver)
    speed, valid = recording.states[..., 2], recording.valid
    standing = ((speed < 0.05) & valid).sum(axis=1)
    assert (standing >= 35).sum() >= 10
    plain = record_traffic("highway", np.random.default_rng(0), 160, 5)
    assert ((plain.states[..., 2] < 0.05) & plain.valid).sum() == 0


def test_a_halting_vehicle_brakes_at_its_comfortable_rate_easing_near_rest():
    import gymnasium
    import highway_env  # noqa: F401

    from riskflow_env.scenarios.road_stepper import STOP_EASE_SPEED, traffic_vehicle_class

    road = gymnasium.make("highway-v0").unwrapped.road
    vehicle = traffic_vehicle_class()(road, [0.0, 0.0], 0.0, 20.0, target_speed=20.0)
    vehicle.COMFORT_ACC_MIN = -3.0
    assert vehicle.acceleration(vehicle) == pytest.approx(0.0, abs=1e-9)  # cruising
    vehicle.halting = True
    assert vehicle.acceleration(vehicle) == pytest.approx(-3.0)
    vehicle.speed = STOP_EASE_SPEED / 2
    assert vehicle.acceleration(vehicle) == pytest.approx(-1.5)
    vehicle.speed = 0.0
    assert -0.2 < vehicle.acceleration(vehicle) < 0.0


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"stop_share": 1.5}, "DriverConfig.stop_share must be in [0, 1], got 1.5"),
        ({"stop_duration": (5.0, 1.0)}, "DriverConfig.stop_duration: need 0 <= min <= max"),
        ({"time_gap": (2.0, 1.0)}, "DriverConfig.time_gap: need 0 <= min <= max, got (2.0, 1.0)"),
        ({"extra_headway": (-1.0, 1.0)}, "DriverConfig.extra_headway: need 0 <= min <= max"),
        ({"car_length": (0.0, 4.0)}, "DriverConfig.car_length: need 0 < min <= max"),
        ({"delta": (4.0,)}, "DriverConfig.delta must be a (min, max) pair, got (4.0,)"),
        ({"time_gap": 1.5}, "DriverConfig.time_gap must be a (min, max) pair, got 1.5"),
        ({"politeness": (0.0, np.nan)}, "DriverConfig.politeness must be a finite number"),
        ({"truck_fraction": -0.1}, "DriverConfig.truck_fraction must be in [0, 1], got -0.1"),
        ({"truck_speed_factor": 0.0}, "DriverConfig.truck_speed_factor must be > 0, got 0.0"),
        ({"default_speed_limit": np.inf}, "DriverConfig.default_speed_limit must be a finite"),
    ],
)
def test_driver_config_is_validated(changes, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        DriverConfig(**changes)
    assert DriverConfig(politeness=[0.1, 0.2]).politeness == (0.1, 0.2)  # a list, as from JSON


def test_same_generator_state_same_recording():
    a = record_traffic("u-turn", np.random.default_rng(1), steps=30, warmup_steps=5)
    b = record_traffic("u-turn", np.random.default_rng(1), steps=30, warmup_steps=5)
    c = record_traffic("u-turn", np.random.default_rng(2), steps=30, warmup_steps=5)
    np.testing.assert_array_equal(a.states, b.states)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert a.kinds == b.kinds
    assert a.states.shape != c.states.shape or not np.array_equal(a.states, c.states)


def test_windows_keep_the_ego_and_the_vehicles_around_it():
    recording = record_traffic("u-turn", np.random.default_rng(0), steps=151, warmup_steps=20)
    config = SceneConfig(radius=60.0)  # 31 + 100 steps
    scenes = cut_scenarios(recording, np.random.default_rng(0), config)
    assert len(scenes) == 3  # starts 0, 10, 20
    entering = leaving = 0
    for scene in scenes:
        now = scene.current_index
        assert scene.states.shape[1] == config.history_steps + config.future_steps
        assert scene.valid[0].all() and scene.ego_index == 0  # ego over the whole window
        assert np.all(scene.valid[:, now:].any(axis=1))  # nobody who left before now
        entering += int(np.sum(~scene.valid[:, now] & scene.valid[:, now:].any(axis=1)))
        leaving += int(np.sum(scene.valid[:, now] & ~scene.valid[:, -1]))
        ego = scene.states[0, :, :2]
        gaps = np.linalg.norm(scene.states[..., :2] - ego, axis=-1)
        assert np.all(np.where(scene.valid, gaps, np.inf).min(axis=1) <= config.radius)
        assert scene.source == "highway-env-idm" and scene.family == "u-turn"
        assert np.all(
            np.abs(scene.states[np.arange(scene.num_agents), scene.valid.argmax(1), 3])
            <= np.pi + 1e-6
        )  # first headings wrapped
    assert entering + leaving > 0


def test_window_outside_the_recording_is_an_error(merge_recording):
    with pytest.raises(ValueError, match="does not fit"):
        cut_scenario(merge_recording, 110, np.random.default_rng(0), TINY)


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_gives_a_scene(family):
    scene = generate_scenario(family, np.random.default_rng(0), TINY, name=f"{family}-x")
    assert scene.family == family and scene.name == f"{family}-x"
    assert scene.history_steps == 31 and scene.future_steps == 20
    assert scene.num_agents >= 2
    np.testing.assert_array_equal(scene.states, scene.states.astype(np.float32))


def test_scene_config_is_validated():
    with pytest.raises(ValueError, match="future_steps"):
        SceneConfig(future_steps=0)
    with pytest.raises(ValueError, match="warmup"):
        SceneConfig(warmup=(10, 5))


@pytest.mark.parametrize("family", ["roundabout", "intersection", "merge", "exit"])
def test_road_stepper_queries_match_highway_env(family):
    """The cached / vectorised queries give highway-env's own answers."""
    import gymnasium
    import highway_env  # noqa: F401

    from riskflow_env.maps.highway import ENV_IDS

    env = gymnasium.make(ENV_IDS[family], config={"vehicles_count": 12}).unwrapped
    env.reset(seed=0)
    road = env.road
    road.neighbour_vehicles_connected_lanes = True
    base = type(road).neighbour_vehicles
    stepper = RoadStepper(road)
    for _ in range(3):
        for _ in range(5):
            stepper.lane_tables = {}  # the per-step cache
            road.act()
            road.step(0.1)
        stepper.lane_tables = {}
        for vehicle in road.vehicles:
            for lane_index in {vehicle.lane_index, *road.network.side_lanes(vehicle.lane_index)}:
                assert stepper.neighbours(vehicle, lane_index) == base(road, vehicle, lane_index)
        expected = [
            road.network.get_closest_lane_index(v.position, v.heading) for v in road.vehicles
        ]
        xy = np.array([v.position for v in road.vehicles])
        stepper.update_lanes(road.vehicles, xy)
        assert [v.lane_index for v in road.vehicles] == expected
    env.close()
