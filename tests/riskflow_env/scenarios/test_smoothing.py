"""Kinematic reference filtering: exact on cubics, quiet on interpolated keyframes."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.dynamics import inverse, rollout
from riskflow_env.metrics.kinematics import kinematic_p95
from riskflow_env.scenarios.scenarionet import scenario_from_description
from riskflow_env.scenarios.smoothing import POLY_ORDER, smooth_tracks
from tests.riskflow_env.scenarios.scenarionet_sources import description

DT = 0.1


def _states(xy: np.ndarray) -> np.ndarray:
    """(1, T, 4) logged-style states: speed and heading from finite differences."""
    velocity = np.gradient(xy, DT, axis=0)
    speed = np.linalg.norm(velocity, axis=1)
    heading = np.unwrap(np.arctan2(velocity[:, 1], velocity[:, 0]))
    return np.concatenate([xy, speed[:, None], heading[:, None]], axis=1)[None]


def test_cubic_track_is_reproduced_with_its_exact_derivative():
    t = np.arange(60) * DT
    xy = np.stack([3 + 8 * t + 0.5 * t**2 - 0.05 * t**3, 1 + 2 * t + 0.1 * t**2], axis=1)
    states = _states(xy)
    smooth = smooth_tracks(states, np.ones((1, 60), bool))
    np.testing.assert_allclose(smooth[0, :, :2], xy, atol=1e-9)
    velocity = np.stack([8 + t - 0.15 * t**2, 2 + 0.2 * t], axis=1)  # closed form
    np.testing.assert_allclose(smooth[0, :, 2], np.linalg.norm(velocity, axis=1), atol=1e-9)
    chord = np.diff(xy, axis=0)  # heading along each step's motion
    np.testing.assert_allclose(smooth[0, :-1, 3], np.arctan2(chord[:, 1], chord[:, 0]), atol=1e-9)


def test_curved_track_rolls_out_into_itself():
    """Headings along each step's motion: a 33 m circle at 10 m/s, rolled out from its own
    actions over a 5.2 s plan, stays on itself (the tangent heading drifted 0.7 m)."""
    t = np.arange(80) * DT
    radius, rate = 10.0 / 0.3, 0.3
    xy = np.stack([radius * np.sin(rate * t), radius * (1 - np.cos(rate * t))], axis=1)
    states = np.concatenate([xy, np.full((80, 1), 10.0), (rate * t)[:, None]], axis=1)[None]
    smooth = smooth_tracks(states, np.ones((1, 80), bool))[0]
    for plan in (smooth[10:63], smooth[27:]):  # one that ends with the track
        replayed = rollout(plan[0], inverse(plan))
        assert np.abs(replayed[:, :2] - plan[1:, :2]).max() < 0.01
    yaw_rate = inverse(smooth)[:, 1]  # the edge windows' cubic bends a circle a little
    np.testing.assert_allclose(yaw_rate, rate, atol=0.02)  # the last step's too, not halved


def test_interpolated_keyframes_lose_their_jerk():
    rng = np.random.default_rng(0)
    keys = np.arange(0, 20.01, 0.5)  # 2 Hz keyframes with 0.1 m detection noise
    key_xy = np.stack([10 * keys + 0.3 * keys**2, np.zeros_like(keys)], 1)
    key_xy += rng.normal(0, 0.1, key_xy.shape)
    t = np.arange(201) * DT
    xy = np.stack([np.interp(t, keys, key_xy[:, i]) for i in range(2)], axis=1)
    states, valid = _states(xy), np.ones((1, 201), bool)
    smooth = smooth_tracks(states, valid)
    raw_p95, smooth_p95 = kinematic_p95(states, valid, DT), kinematic_p95(smooth, valid, DT)
    assert smooth_p95["jerk"] < raw_p95["jerk"] / 10
    assert smooth_p95["longitudinal_acceleration"] < raw_p95["longitudinal_acceleration"]
    assert np.abs(smooth[0, :, :2] - xy).max() < 0.3


def test_invalid_steps_and_short_runs_are_left_alone():
    t = np.arange(40) * DT
    xy = np.stack([5 * t + 0.2 * np.sin(7 * t), np.zeros_like(t)], axis=1)
    states = _states(xy)
    valid = np.ones((1, 40), bool)
    valid[0, 10:12] = False  # runs 0-9 (10 steps), 12-13 (2 steps), 14-39 (26 steps)
    valid[0, 14] = False
    smooth = smooth_tracks(states, valid)
    np.testing.assert_array_equal(smooth[~valid], states[~valid])
    np.testing.assert_array_equal(smooth[0, 12:14], states[0, 12:14])  # <= POLY_ORDER + 1
    assert POLY_ORDER + 1 >= 2
    assert not np.allclose(smooth[0, :10, :2], states[0, :10, :2])  # a 9-step window
    assert not np.allclose(smooth[0, 15:, :2], states[0, 15:, :2])


def test_standing_vehicle_keeps_its_logged_heading():
    states = np.zeros((1, 30, 4))
    states[0, :, 3] = 1.2
    smooth = smooth_tracks(states, np.ones((1, 30), bool))
    np.testing.assert_array_equal(smooth[0, :, 3], 1.2)
    np.testing.assert_array_equal(smooth[0, :, 2], 0.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"window": 20}, "window"),
        ({"window": 3}, "window"),
        ({"polyorder": 0}, "polyorder"),
        ({"dt": 0.0}, "dt"),
    ],
)
def test_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        smooth_tracks(np.zeros((1, 30, 4)), np.ones((1, 30), bool), **kwargs)


def test_bad_shapes():
    with pytest.raises(ValueError, match=r"\(N, T, 4\)"):
        smooth_tracks(np.zeros((30, 4)), np.ones(30, bool))


def test_loader_option_keeps_validity_and_stays_close():
    data = description("nuscenes")
    raw = scenario_from_description(data)
    smooth = scenario_from_description(data, smooth=True)
    np.testing.assert_array_equal(smooth.valid, raw.valid)
    gap = np.linalg.norm(smooth.states[..., :2] - raw.states[..., :2], axis=-1)
    gap = np.where(raw.valid, gap, 0.0)
    straight = [raw.agent_ids.index(name) for name in ("ego", "car")]
    assert gap[straight].max() < 1e-6  # constant velocity: reproduced
    assert gap.max() < 1.0  # the parker's path has sharp corners: the fit rounds them
    assert np.all(np.isfinite(smooth.states))


@pytest.mark.reliability
def test_dt_is_a_number_not_a_bool():
    states, valid = np.zeros((1, 9, 4)), np.ones((1, 9), bool)
    for dt in (True, np.bool_(True), "0.1", 10**400, float("nan")):
        with pytest.raises(ValueError, match=r"dt must be a finite number > 0 \[s\]"):
            smooth_tracks(states, valid, dt)
    np.testing.assert_array_equal(smooth_tracks(states, valid, np.float32(0.1)), states)
