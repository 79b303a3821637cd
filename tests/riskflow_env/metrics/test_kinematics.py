"""KDD on unicycle tracks whose accelerations and jerk are known."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.metrics import (
    KINEMATIC_FEATURES,
    KinematicSamples,
    kdd,
    kdd_over_records,
    kinematic_samples,
)
from riskflow_env.metrics.kinematics import kinematic_p95
from tests.riskflow_env.metrics.records import record_of

STEPS = 40


def actions(accel, yaw_rate=0.0, steps=STEPS - 1):
    out = np.zeros((steps, 2))
    out[:, 0], out[:, 1] = accel, yaw_rate
    return out


def test_constant_speed_against_constant_speed_is_zero(straight):
    record = record_of(straight(0.0, 10.0, STEPS)[None], straight(3.0, 7.0, STEPS)[None])
    result = kdd(kinematic_samples(record))
    assert result == {name: pytest.approx(0.0, abs=1e-12) for name in (*KINEMATIC_FEATURES, "kdd")}


def test_known_longitudinal_lateral_and_jerk_distances(rolled):
    start = np.array([0.0, 0.0, 10.0, 0.0])
    cruise = rolled(start, actions(0.0))[None]
    braking = rolled(start, actions(-1.0))[None]  # a = -1 m/s^2: W1 = 1 on accel only
    result = kdd(kinematic_samples(record_of(braking, cruise)))
    assert result["longitudinal_acceleration"] == pytest.approx(1.0)
    assert result["lateral_acceleration"] == pytest.approx(0.0, abs=1e-9)
    assert result["jerk"] == pytest.approx(0.0, abs=1e-9)
    assert result["kdd"] == pytest.approx(1.0 / 3)
    turning = rolled(start, actions(0.0, 0.1))[None]  # v * omega = 1 m/s^2 sideways
    assert kdd(kinematic_samples(record_of(turning, cruise)))["lateral_acceleration"] == (
        pytest.approx(1.0)
    )
    ramp = rolled(start, actions(0.1 * np.arange(STEPS - 1)))[None]  # jerk 1 m/s^3
    ramp_result = kdd(kinematic_samples(record_of(ramp, cruise)))
    assert ramp_result["jerk"] == pytest.approx(1.0)


def test_samples_respect_context_evaluated_and_validity(straight):
    tracks = np.stack([straight(0.0, 10.0, 10), straight(0.0, 5.0, 10)])
    record = record_of(tracks, tracks, num_context=3, evaluated=np.array([True, False]))
    samples = kinematic_samples(record)
    # accel samples end at steps 3..9 (7 of them); jerk samples end at 3..9 too.
    assert samples.generated["longitudinal_acceleration"].size == 7
    assert samples.generated["jerk"].size == 7
    arrays = samples.as_arrays()
    assert KinematicSamples.from_arrays(arrays).generated["jerk"].size == 7
    pooled = KinematicSamples.concatenate([samples, samples])
    assert pooled.reference["lateral_acceleration"].size == 14
    assert np.isnan(kdd([])["kdd"])


def test_pooled_over_records(rolled, straight):
    start = np.array([0.0, 0.0, 10.0, 0.0])
    cruise = rolled(start, actions(0.0))[None]
    braking = rolled(start, actions(-2.0))[None]
    # Generated accelerations: half 0, half -2; reference all 0: W1 = 0.5 * 2 = 1.
    result = kdd_over_records([record_of(cruise, cruise), record_of(braking, cruise)])
    assert result["longitudinal_acceleration"] == pytest.approx(1.0)


def test_samples_of_a_constant_turn_and_a_constant_braking_and_their_p95(rolled):
    """Agent 0 turns at omega = 0.2 rad/s at a constant 10 m/s (lateral v omega = 2
    m/s^2), agent 1 brakes straight at a = -3 m/s^2 from 20 m/s: every sample sits at
    these values, jerk is 0, and the p95 of |value| over both agents is 3 (longitudinal)
    and 2 (lateral)."""
    turning = rolled(np.array([0.0, 0.0, 10.0, 0.0]), actions(0.0, 0.2))
    braking = rolled(np.array([0.0, 10.0, 20.0, 0.0]), actions(-3.0))
    tracks = np.stack([turning, braking])
    samples = kinematic_samples(record_of(tracks, tracks)).generated
    steps = STEPS - 1
    expected_long = np.concatenate([np.zeros(steps), np.full(steps, -3.0)])
    expected_lat = np.concatenate([np.full(steps, 2.0), np.zeros(steps)])
    np.testing.assert_allclose(samples["longitudinal_acceleration"], expected_long, atol=1e-9)
    np.testing.assert_allclose(samples["lateral_acceleration"], expected_lat, atol=1e-9)
    np.testing.assert_allclose(samples["jerk"], 0.0, atol=1e-8)
    p95 = kinematic_p95(tracks, np.ones(tracks.shape[:2], bool), 0.1)
    assert p95 == {
        "longitudinal_acceleration": pytest.approx(3.0),
        "lateral_acceleration": pytest.approx(2.0),
        "jerk": pytest.approx(0.0, abs=1e-8),
    }
    assert np.isnan(kinematic_p95(tracks, np.zeros(tracks.shape[:2], bool), 0.1)["jerk"])
