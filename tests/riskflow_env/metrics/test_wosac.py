"""WOSAC-style realism: features, estimators and scene scores with known answers."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from riskflow_env.compiled import SWITCH
from riskflow_env.metrics import WOSAC_2024, FeatureConfig, wosac_scene
from riskflow_env.metrics.wosac import (
    bernoulli_log_likelihood,
    histogram_log_likelihood,
    wosac_aggregate,
)
from riskflow_env.metrics.wosac_features import (
    MAX_TTC,
    box_signed_distance,
    interaction_features,
    kinematic_features,
    wosac_features,
)
from tests.riskflow_env.metrics.records import record_of

STEPS = 30


def test_weights_are_the_2024_challenge_weights():
    assert sum(f.weight for f in WOSAC_2024.values()) == pytest.approx(1.0)
    assert WOSAC_2024["collision_indication"].weight == 0.25
    assert WOSAC_2024["linear_speed"].weight == 0.05


def test_box_signed_distance_cases():
    def pair(second):
        states = np.array([[[0.0, 0.0, 0.0, 0.0]], [second]])  # (A=2, T=1, 4)
        return box_signed_distance(states, np.array([4.0, 4.0]), np.array([2.0, 2.0]))[0, 0, 1]

    assert pair([10.0, 0.0, 0.0, 0.0]) == pytest.approx(6.0)  # apart along x
    assert pair([6.0, 4.0, 0.0, 0.0]) == pytest.approx(math.sqrt(8.0))  # corner to corner
    assert pair([3.0, 0.0, 0.0, 0.0]) == pytest.approx(-1.0)  # 1 m penetration
    assert pair([5.0, 0.0, 0.0, math.pi / 2]) == pytest.approx(2.0)  # rotated: x half-extent 1


def test_ttc_follows_the_vehicle_ahead_only():
    def ttc(leader):
        states = np.array([[[0.0, 0.0, 10.0, 0.0]], [leader]])
        out = interaction_features(states, np.ones((2, 1), bool), np.full(2, 4.0), np.full(2, 2.0))
        return out["time_to_collision"][0, 0]

    assert ttc([20.0, 0.0, 5.0, 0.0]) == pytest.approx(16.0 / 5.0)  # gap 16 m, closing 5 m/s
    assert ttc([20.0, 0.0, 15.0, 0.0]) == MAX_TTC  # opening
    assert ttc([20.0, 5.0, 5.0, 0.0]) == MAX_TTC  # beside the trail
    assert ttc([20.0, 0.0, 5.0, math.pi]) == MAX_TTC  # oncoming: heading too different
    assert ttc([-20.0, 0.0, 0.0, 0.0]) == MAX_TTC  # behind


def test_kinematic_features_of_a_constant_turn(rolled):
    actions = np.tile([0.0, 0.2], (STEPS - 1, 1))
    track = rolled(np.array([0.0, 0.0, 10.0, 3.1]), actions)[None]  # heading wraps past pi
    features = kinematic_features(track, np.ones((1, STEPS), bool), 0.1)
    speed, speed_ok = features["linear_speed"]
    assert not speed_ok[0, 0] and speed_ok[0, 1:-1].all() and not speed_ok[0, -1]
    np.testing.assert_allclose(speed[0, 1:-1], 10.0, rtol=1e-3)  # chord of the arc
    np.testing.assert_allclose(features["angular_speed"][0][0, 1:-1], 0.2, rtol=1e-9)
    accel, accel_ok = features["angular_acceleration"]
    np.testing.assert_allclose(accel[0][accel_ok[0]], 0.0, atol=1e-9)
    assert accel_ok.sum() == STEPS - 4


def test_kinematic_features_of_constant_accelerations():
    """Agent 0 drives straight at a = 1.5 m/s^2 from 5 m/s; agent 1 turns in place at
    alpha = 0.5 rad/s^2 from rest. Central differences are exact on these quadratics:
    speed 5 + a t, linear acceleration a, angular speed alpha t, angular acceleration
    alpha, wherever the neighbouring steps exist."""
    dt, accel, alpha = 0.1, 1.5, 0.5
    time = dt * np.arange(STEPS)
    tracks = np.zeros((2, STEPS, 4))
    tracks[0, :, 0] = 5.0 * time + 0.5 * accel * time**2
    tracks[1, :, 3] = 0.5 * alpha * time**2
    features = kinematic_features(tracks, np.ones((2, STEPS), bool), dt)
    inner, inner2 = slice(1, -1), slice(2, -2)
    np.testing.assert_allclose(features["linear_speed"][0][0, inner], 5.0 + accel * time[inner])
    np.testing.assert_allclose(features["linear_acceleration"][0][0, inner2], accel)
    np.testing.assert_allclose(features["angular_speed"][0][1, inner], alpha * time[inner])
    np.testing.assert_allclose(features["angular_acceleration"][0][1, inner2], alpha)
    np.testing.assert_allclose(features["linear_speed"][0][1, inner], 0.0, atol=1e-12)
    np.testing.assert_allclose(features["angular_speed"][0][0, inner], 0.0, atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_nearest_object_equals_the_reference(seed, monkeypatch):
    """The numba kernel (riskflow_env.metrics.wosac_kernels) against the numpy pairs:
    crowded random boxes, some overlapping, some agents absent at some steps."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(seed)
    agents, steps = 14, 25
    states = np.zeros((agents, steps, 4))
    states[..., :2] = rng.uniform(-15.0, 15.0, (agents, 1, 2)) + np.cumsum(
        rng.normal(0.0, 0.4, (agents, steps, 2)), axis=1
    )
    states[..., 3] = rng.uniform(-np.pi, np.pi, (agents, 1)) + rng.normal(0, 0.1, (agents, steps))
    valid = rng.random((agents, steps)) < 0.85
    sizes = rng.uniform(3.5, 6.0, agents), rng.uniform(1.6, 2.4, agents)
    out = {}
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        out[switch] = interaction_features(states, valid, *sizes)
    reference, compiled = out["0"], out["1"]
    distance = reference["distance_to_nearest_object"]
    assert (distance < 0).any() and np.isfinite(distance).any() and np.isinf(distance).any()
    np.testing.assert_allclose(compiled["distance_to_nearest_object"], distance, rtol=0, atol=1e-9)
    for name in ("collision_indication", "time_to_collision"):
        np.testing.assert_array_equal(compiled[name], reference[name])
    states[3, 5, 0] = np.nan  # a NaN state makes its step's distances NaN in both
    out = {}
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        out[switch] = interaction_features(states, valid, *sizes)["distance_to_nearest_object"]
    np.testing.assert_array_equal(np.isnan(out["1"]), np.isnan(out["0"]))
    assert np.isnan(out["0"][:, 5]).any() or not valid[3, 5]


def test_nearest_object_collision_flag_and_road_edge(road):
    """Three 4 m x 2 m boxes on the 10 m wide box road, heading along it: a touches b
    nose to tail (distance 0: a collision, as in the env), c stands beside b, 2.5 m
    between the boxes; a alone has nothing near. Road edge: the SDF of the footprint
    point furthest out, a corner."""
    states = np.zeros((3, 1, 4))
    states[:, 0, :2] = [[10.0, 0.0], [14.0, 0.0], [14.0, 4.5]]  # a, b, c
    sizes = np.full(3, 4.0), np.full(3, 2.0)
    out = interaction_features(states, np.ones((3, 1), bool), *sizes)
    np.testing.assert_allclose(out["distance_to_nearest_object"][:, 0], [0.0, 0.0, 2.5])
    assert out["collision_indication"][:, 0].tolist() == [True, True, False]
    valid = np.array([[True], [False], [False]])  # only a is in the scene
    alone = interaction_features(states, valid, *sizes)
    assert alone["distance_to_nearest_object"][0, 0] == np.inf
    assert not alone["collision_indication"][0, 0]
    features = wosac_features(states, np.ones((3, 1), bool), *sizes, 0.1, road)
    edge, offroad = features["distance_to_road_edge"][0], features["offroad_indication"][0]
    # a, b: corners at |y| = 1, 4 m inside; c: corners at y = 5.5, 0.5 m outside
    np.testing.assert_allclose(edge[:, 0], [-4.0, -4.0, 0.5], atol=0.25)  # 0.5 m raster
    assert offroad[:, 0].tolist() == [False, False, True]


def test_histogram_and_bernoulli_estimators():
    config = FeatureConfig(1.0, 0.0, 1.0, 2, 1.0)
    sim = np.array([0.2, 0.3, 0.4]).reshape(3, 1, 1)  # 3 rollouts, 1 agent, 1 step
    log_lik = histogram_log_likelihood(np.array([[0.1], [0.9]]).T, sim.repeat(2, 2),
                                       np.ones((3, 1, 2), bool), config)  # fmt: skip
    # 6 samples in bin 0 (+1), none in bin 1 (+1): p = 7/8 and 1/8.
    np.testing.assert_allclose(np.exp(log_lik), [[7 / 8, 1 / 8]])
    flags = np.array([[True], [False], [False], [False]])
    np.testing.assert_allclose(np.exp(bernoulli_log_likelihood(np.array([True]), flags, 0.0)), 0.25)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"weight": -1.0}, "FeatureConfig.weight must be >= 0, got -1.0"),
        ({"weight": math.nan}, "FeatureConfig.weight must be a finite number"),
        ({"num_bins": -2}, "FeatureConfig.num_bins must be an int in [0, 1000000]"),
        ({"num_bins": 2.0}, "FeatureConfig.num_bins must be an int in [0, 1000000]"),
        ({"min_val": 5.0, "max_val": 1.0}, "FeatureConfig needs min_val < max_val, got min_val=5"),
        ({"max_val": math.inf}, "FeatureConfig.max_val must be a finite number"),
        ({"pseudocount": 0.0}, "FeatureConfig.pseudocount must be > 0"),
    ],
)
def test_feature_config_refuses_bad_values_when_built(changes, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        FeatureConfig(**({"weight": 1.0, "num_bins": 10} | changes))


def scene(road, sims, log):
    """Records of one scene: each sim (A, T, 4) against the same log (A, T, 4)."""
    return [record_of(sim, log, drivable_map=road, num_context=3, scene_id="box") for sim in sims]


def _histogram_p(samples: int, bins: int, pseudocount: float = 0.1) -> float:
    """Probability of the bin that holds all ``samples`` of a smoothed histogram."""
    return (samples + pseudocount) / (samples + pseudocount * bins)


def test_rollouts_identical_to_the_log_score_the_closed_form(road, straight):
    """Every feature constant in time and every rollout equal to the log: each histogram
    holds its n samples in the logged value's bin, p = (n + 0.1) / (n + 0.1 * bins), with
    n = N x the scored steps where the feature is defined (27 scored steps 3..29; speeds
    need a step either side, accelerations two); the flags are never set, p = (N + 0.001)
    / (N + 0.002); the metametric and buckets are the weighted means of these."""
    rollouts = 8
    # centres 1.5 m off the middle: corners 2.5 m inside the 10 m road (SDF -2.5, mid-bin)
    log = np.stack([straight(5.0, 8.0, STEPS, y=-1.5), straight(12.0, 8.0, STEPS, y=1.5)])
    scores = wosac_scene(scene(road, [log] * rollouts, log))
    steps = {"linear_speed": 26, "linear_acceleration": 25, "angular_speed": 26,
             "angular_acceleration": 25}  # fmt: skip
    expected = {}
    for name, feature in WOSAC_2024.items():
        if feature.bernoulli:
            expected[name] = (rollouts + 0.001) / (rollouts + 0.002)
        else:
            expected[name] = _histogram_p(rollouts * steps.get(name, 27), feature.num_bins)
    for name, value in expected.items():
        assert scores[f"{name}_likelihood"] == pytest.approx(value, rel=1e-12), name
    weighted = sum(WOSAC_2024[name].weight * value for name, value in expected.items())
    total = sum(feature.weight for feature in WOSAC_2024.values())
    assert scores["metametric"] == pytest.approx(weighted / total, rel=1e-12)
    kinematic = [expected[name] for name in steps]  # four features of equal weight
    assert scores["kinematic"] == pytest.approx(np.mean(kinematic), rel=1e-12)
    assert scores["map_based"] == pytest.approx(
        (0.1 * expected["distance_to_road_edge"] + 0.25 * expected["offroad_indication"]) / 0.35
    )
    assert scores["num_rollouts"] == rollouts
    assert wosac_aggregate([scores, scores])["metametric"] == pytest.approx(scores["metametric"])


def test_speed_likelihood_of_rollouts_half_at_the_logged_speed(road, straight):
    """One rollout at the logged 8 m/s, one at 16 m/s: each agent's speed histogram has
    26 samples in the logged bin and 26 in another, p = (26 + 0.1) / (52 + 10 x 0.1)."""
    log = np.stack([straight(5.0, 8.0, STEPS, y=-1.5), straight(12.0, 8.0, STEPS, y=1.5)])
    fast = log.copy()
    fast[..., 0] = log[:, :1, 0] + 2.0 * (log[..., 0] - log[:, :1, 0])
    scores = wosac_scene(scene(road, [log, fast], log))
    assert scores["linear_speed_likelihood"] == pytest.approx(26.1 / 53.0, rel=1e-12)


def test_shifted_rollouts_score_lower(road, straight):
    log = np.stack([straight(5.0, 8.0, STEPS, y=-2.0), straight(12.0, 8.0, STEPS, y=2.0)])
    exact = wosac_scene(scene(road, [log] * 4, log))
    fast = log.copy()
    fast[..., 0] = log[:, :1, 0] + 2.0 * (log[..., 0] - log[:, :1, 0])  # twice the speed
    fast[..., 2] = 16.0
    faster = wosac_scene(scene(road, [fast] * 4, log))
    assert faster["linear_speed_likelihood"] < 0.01  # 16 m/s lands in another bin
    assert faster["kinematic"] < exact["kinematic"]
    assert faster["metametric"] < exact["metametric"]
    crash = log.copy()
    crash[1, :, :2] = crash[0, :, :2] + [2.0, 1.0]  # agent 1 drives overlapping agent 0
    crashed = wosac_scene(scene(road, [crash] * 4, log))
    # Both agents collide in every rollout but not in the log: p = 0.001 / 4.002.
    assert crashed["collision_indication_likelihood"] == pytest.approx(0.001 / 4.002)
    assert crashed["interactive"] < exact["interactive"]
    off = log.copy()
    off[..., 1] += 10.0  # both outside the 10 m wide road
    off_road = wosac_scene(scene(road, [off] * 4, log))
    assert off_road["offroad_indication_likelihood"] < 1e-3


def test_scene_rollouts_must_share_the_reference(road, straight):
    log = straight(5.0, 8.0, STEPS)[None]
    records = scene(road, [log], log) + scene(road, [log], log + 1.0)
    with pytest.raises(ValueError, match="one scene"):
        wosac_scene(records)
