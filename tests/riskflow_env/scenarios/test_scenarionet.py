"""ScenarioNet loader: restricted unpickling, resampling, windows, sizes, maps, real samples."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from riskflow_env.metrics.kinematics import kinematic_p95
from riskflow_env.scenarios.safe_pickle import loads_data_pickle
from riskflow_env.scenarios.scenarionet import load_scenarionet, scenario_from_description
from riskflow_env.scenarios.scenarionet_map import build_map
from tests.samples import SAMPLES, SCENARIONET_DIR, require_samples

DATA_DIR = SCENARIONET_DIR


def _track(xy, heading, valid, kind="VEHICLE", length=4.0, width=2.0, velocity=True):
    xy = np.asarray(xy, dtype=float)
    steps = len(xy)
    state = {
        "position": np.concatenate([xy, np.zeros((steps, 1))], axis=1),
        "heading": np.asarray(heading, dtype=float),
        "valid": np.asarray(valid, dtype=float),
        "length": np.full((steps, 1), length),
        "width": np.full((steps, 1), width),
        "height": np.full((steps, 1), 1.5),
    }
    if velocity:
        state["velocity"] = np.gradient(xy, 0.5, axis=0)
    return {"type": kind, "state": state, "metadata": {}}


def _description(steps=21, rate=0.5, velocity=True, exit_lanes=True):
    """2 Hz scene: ego along +x at 10 m/s, a car crossing the +-pi heading, a pedestrian."""
    t = np.arange(steps) * rate
    ego = _track(np.stack([10 * t, np.zeros(steps)], 1), np.zeros(steps), np.ones(steps))
    ego["state"]["length"][:], ego["state"]["width"][:] = 1.8, 4.5  # swapped, as nuScenes SDC
    heading = np.where(np.arange(steps) % 2 == 0, np.pi - 0.05, -np.pi + 0.05)
    other_valid = np.ones(steps)
    other_valid[-3:] = 0
    other = _track(np.stack([100 - 5 * t, np.full(steps, 3.5)], 1), heading, other_valid)
    walker = _track(np.zeros((steps, 2)), np.zeros(steps), np.ones(steps), kind="PEDESTRIAN")
    for track in (ego, other, walker):
        if not velocity:
            del track["state"]["velocity"]
    lane_a = {"type": "LANE_SURFACE_STREET", "polyline": np.array([[-20.0, 0, 0], [60.0, 0, 0]])}
    lane_a["polygon"] = np.array([[-20.0, -2], [60, -2], [60, 2], [-20, 2]])
    lane_b = {"type": "LANE_SURFACE_STREET", "polyline": np.array([[60.0, 0], [220.0, 0]])}
    lane_c = {"type": "LANE_SURFACE_STREET", "polyline": np.array([[220.0, 3.5], [-20.0, 3.5]])}
    lane_b["speed_limit_kmh"] = 36.0
    if exit_lanes:
        lane_a["exit_lanes"] = ["b"]
    features = {"a": lane_a, "b": lane_b, "c": lane_c}
    features["edge"] = {"type": "ROAD_EDGE_BOUNDARY", "polyline": np.array([[0.0, -5], [9, -5]])}
    return {
        "id": "toy",
        "tracks": {"ego": ego, "car": other, "walker": walker},
        "map_features": features,
        "metadata": {"sdc_id": "ego", "ts": t, "sample_rate": rate, "scenario_id": "toy"},
    }


def test_synthetic_description_resampled_to_10hz(tmp_path):
    path = tmp_path / "toy.pkl"
    path.write_bytes(pickle.dumps(_description()))
    scenario = load_scenarionet(path, resolution=0.5)
    recorded = 101  # 10 s at 10 Hz
    assert scenario.agent_ids == ("ego", "car")  # pedestrian dropped, SDC first
    assert scenario.ego_index == 0 and scenario.dt == 0.1 and scenario.history_steps == 31
    assert scenario.states.shape == (2, 31 + 100, 4)  # rest is 70 steps, padded to 100
    assert scenario.valid[0, :recorded].all() and not scenario.valid[:, recorded:].any()
    np.testing.assert_allclose(scenario.states[0, :recorded, 0], np.arange(recorded), atol=1e-9)
    np.testing.assert_allclose(scenario.states[0, :recorded, 2], 10.0, atol=1e-9)
    # heading interpolated along the short arc across +-pi, then unwrapped: continuous
    assert np.all(np.abs(np.diff(scenario.states[1, :86, 3])) < 0.021)  # 0.1 rad per 0.5 s
    assert scenario.valid[1, :86].all() and not scenario.valid[1, 86:].any()  # 8.5 s
    assert np.all(np.isfinite(scenario.states))  # invalid steps hold the last valid state
    np.testing.assert_allclose(scenario.states[1, 86:], scenario.states[1, 85][None].repeat(45, 0))
    np.testing.assert_allclose(scenario.length, [4.5, 4.0])  # swapped back for the SDC
    np.testing.assert_allclose(scenario.width, [1.8, 2.0])


def test_map_lanes_successors_and_speed_limits():
    scenario = scenario_from_description(_description())
    lanes = {lane.lane_id: lane for lane in scenario.map.lanes}
    assert set(lanes) == {"a", "b", "c"}
    assert lanes["a"].successors == ("b",) and lanes["b"].successors == ()
    assert lanes["b"].speed_limit == pytest.approx(10.0)
    assert lanes["a"].width == pytest.approx(4.0)  # polygon area / centreline length
    assert lanes["b"].width == pytest.approx(4.0)  # the median of the known widths
    assert scenario.map.is_drivable(np.array([[0.0, 0.0], [150.0, 0.0], [0.0, 3.5]])).all()
    assert not scenario.map.is_drivable(np.array([0.0, -6.0]))
    inferred = scenario_from_description(_description(exit_lanes=False))
    assert {lane.lane_id: lane.successors for lane in inferred.map.lanes}["a"] == ("b",)


def test_speed_from_positions_without_velocity():
    scenario = scenario_from_description(_description(velocity=False))
    np.testing.assert_allclose(scenario.states[0, :101, 2], 10.0, atol=1e-9)


def test_current_index_pads_history_and_checks_range():
    scenario = scenario_from_description(_description(), current_index=5)
    assert not scenario.valid[0, :25].any() and scenario.valid[0, 25:31].all()
    assert scenario.states.shape[1] == 31 + 100  # 95 recorded steps left, padded to 100
    with pytest.raises(ValueError, match="current_index"):
        scenario_from_description(_description(), current_index=500)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.pop("tracks"), "'tracks'"),
        (lambda d: d["metadata"].update(sdc_id="walker"), "sdc_id"),
        (lambda d: d["tracks"]["car"]["state"].update(heading=np.zeros(3)), "heading"),
        (lambda d: d["metadata"].update(ts=np.zeros(21)), "time stamps"),
    ],
)
def test_malformed_descriptions(change, message):
    description = _description()
    change(description)
    with pytest.raises(ValueError, match=message):
        scenario_from_description(description)


def test_numpy_float_arguments_are_numbers():
    scenario = scenario_from_description(
        _description(), resolution=np.float32(0.5), margin=np.float16(5), crop_margin=np.float32(60)
    )
    assert type(scenario.map.resolution) is float and scenario.map.resolution == 0.5
    with pytest.raises(ValueError, match="resolution must be a finite number"):
        scenario_from_description(_description(), resolution=np.bool_(True))


def test_road_edge_fallback():
    xy = np.array([[1.0, 1.0], [5.0, 5.0]])
    square = np.array([[0.0, 0], [10, 0], [10, 10], [0, 10], [0, 0]])
    features = {"edge": {"type": "ROAD_EDGE_BOUNDARY", "polyline": square}}
    drivable_map = build_map(features, resolution=0.5, vehicle_xy=xy)
    assert drivable_map.is_drivable(xy).all() and not drivable_map.lanes


class _Exploit:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_restricted_unpickler_refuses_code(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps({"tracks": {}, "evil": _Exploit(marker)})
    with pytest.raises(ValueError, match=r"disallowed global '(posix|nt|os)\.system'"):
        loads_data_pickle(payload)
    path = tmp_path / "evil.pkl"
    path.write_bytes(payload)
    with pytest.raises(ValueError, match="disallowed global"):
        load_scenarionet(path)
    assert not marker.exists()


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_restricted_unpickler_reads_arrays_at_every_protocol(protocol):
    data = {"a": np.arange(6.0).reshape(2, 3)[:, ::2], "s": np.float32(2.5), "set": {1, 2}}
    loaded = loads_data_pickle(pickle.dumps(data, protocol=protocol))
    np.testing.assert_array_equal(loaded["a"], data["a"])
    assert loaded["s"] == np.float32(2.5) and loaded["set"] == {1, 2}


@pytest.fixture(scope="module")
def samples():
    require_samples()
    return [load_scenarionet(path) for path in SAMPLES]


def test_real_samples_load(samples):
    for scenario in samples:
        assert scenario.name.startswith("scenarionet/scene-")
        assert scenario.states.shape[1] >= 131 and scenario.valid[0, 30]
        assert scenario.num_agents >= 2 and len(scenario.map.lanes) > 100
        assert any(lane.successors for lane in scenario.map.lanes)


def test_real_samples_moving_vehicles_are_on_the_map(samples):
    for scenario in samples:
        moving = scenario.valid & (scenario.states[..., 2] > 1.0)
        inside = scenario.map.is_drivable(scenario.states[..., :2][moving])
        assert inside.mean() >= 0.95, f"{scenario.name}: {inside.mean():.3f} on the map"


def test_real_samples_filtered_references_are_smooth(samples):
    for path, scenario in zip(SAMPLES, samples, strict=True):
        smooth = load_scenarionet(path, smooth=True)
        moving = scenario.valid & (scenario.states[..., 2] > 1.0) & (smooth.states[..., 2] > 1.0)
        raw_p95 = kinematic_p95(scenario.states, moving, scenario.dt)
        smooth_p95 = kinematic_p95(smooth.states, moving, smooth.dt)
        assert smooth_p95["jerk"] < raw_p95["jerk"] / 5, (scenario.name, raw_p95, smooth_p95)
        assert smooth_p95["longitudinal_acceleration"] < 4.0, (scenario.name, smooth_p95)
