"""Scenario files: lossless round trips, shared maps, and a clear error for every bad file."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from riskflow_env.maps import Lane, from_lanes
from riskflow_env.scenarios import (
    Scenario,
    ScenarioFormatError,
    list_scenarios,
    load_bank,
    load_scenario,
    save_scenario,
)
from riskflow_env.scenarios.io import load_map


def _map(name: str = "toy", shift: float = 0.0):
    lanes = (
        Lane(np.array([[0.0, shift], [60.0, shift]]), 4.0, "a->b#0", 20.0, ("b->c#0",)),
        Lane(np.array([[60.0, shift], [80.0, shift + 5.0], [100.0, shift + 5.0]]), 3.5, "b->c#0"),
    )
    return from_lanes(lanes, resolution=0.5, name=name)


def _scenario(drivable_map=None, steps: int = 40, float32: bool = False, **changes) -> Scenario:
    rng = np.random.default_rng(0)
    states = rng.normal(size=(3, steps, 4)) * [10.0, 1.0, 2.0, 0.1] + [30.0, 0.0, 10.0, 0.0]
    if float32:
        states = states.astype(np.float32).astype(np.float64)
    valid = np.ones((3, steps), dtype=bool)
    valid[1, 25:] = False  # leaves
    valid[2, :33] = False  # enters after the current step
    states[~valid] = 0.0
    fields = dict(
        map=drivable_map or _map(),
        states=states,
        valid=valid,
        length=np.array([4.5, 5.0, 12.0]),
        width=np.array([1.9, 2.0, 2.5]),
        ego_index=0,
        agent_ids=("a", "b", "c"),
        name="toy-0",
        dt=0.1,
        history_steps=31,
        kinds=("car", "car", "truck"),
        source="unit-test",
        family="toy",
    )
    fields.update(changes)
    return Scenario(**fields)


def assert_same_scenario(a: Scenario, b: Scenario) -> None:
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_array_equal(a.states[a.valid], b.states[b.valid])
    assert np.all(b.states[~b.valid] == 0.0)
    for name in ("length", "width"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("ego_index", "agent_ids", "kinds", "name", "source", "family", "dt"):
        assert getattr(a, name) == getattr(b, name), name
    assert a.history_steps == b.history_steps
    assert_same_map(a.map, b.map)


def assert_same_map(a, b) -> None:
    np.testing.assert_array_equal(a.drivable, b.drivable)
    np.testing.assert_array_equal(a.origin, b.origin)
    np.testing.assert_array_equal(a.sdf, b.sdf)
    assert (a.resolution, a.name) == (b.resolution, b.name)
    assert len(a.lanes) == len(b.lanes)
    for lane_a, lane_b in zip(a.lanes, b.lanes, strict=True):
        np.testing.assert_array_equal(lane_a.centerline, lane_b.centerline)
        assert (lane_a.lane_id, lane_a.width, lane_a.speed_limit, lane_a.successors) == (
            lane_b.lane_id,
            lane_b.width,
            lane_b.speed_limit,
            lane_b.successors,
        )


@pytest.mark.parametrize("float32", [False, True])
def test_round_trip_with_inline_map(tmp_path, float32):
    scenario = _scenario(float32=float32)
    path = save_scenario(scenario, tmp_path / "scene.npz")
    loaded = load_scenario(path)
    assert_same_scenario(scenario, loaded)
    with np.load(path) as data:
        assert data["states"].dtype == (np.float32 if float32 else np.float64)
        assert "map_sdf" not in data.files  # recomputed on load


def test_round_trip_of_empty_labels_and_stored_sdf(tmp_path):
    scenario = _scenario(agent_ids=(), kinds=(), name="", family="", source="")
    path = save_scenario(scenario, tmp_path / "scene.npz", include_sdf=True)
    assert_same_scenario(scenario, load_scenario(path))
    with np.load(path) as data:
        assert "map_sdf" in data.files


def test_shared_maps_are_written_once_and_loaded_once(tmp_path):
    first, second = _scenario(name="one"), _scenario(name="two")
    other = _scenario(drivable_map=_map(shift=3.0), name="three")
    for scene in (first, second, other):
        save_scenario(scene, tmp_path / f"{scene.name}.npz", map_dir=tmp_path / "maps")
    maps = sorted((tmp_path / "maps").glob("*.npz"))
    assert len(maps) == 2 and all(len(p.stem) == 16 for p in maps)
    one, two, three = (load_scenario(tmp_path / f"{n}.npz") for n in ("one", "two", "three"))
    assert one.map is two.map and one.map is not three.map
    assert_same_scenario(first, one)
    assert_same_scenario(other, three)


def test_same_scenario_gives_byte_identical_files(tmp_path):
    scenario = _scenario()
    save_scenario(scenario, tmp_path / "a.npz", map_dir=tmp_path / "maps")
    save_scenario(scenario, tmp_path / "b.npz", map_dir=tmp_path / "maps")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    assert not list(tmp_path.glob(".*"))  # no temp file left


def test_list_and_load_bank(tmp_path):
    for name in ("b", "a", "c"):
        save_scenario(_scenario(name=name), tmp_path / f"{name}.npz", map_dir=tmp_path / "maps")
    (tmp_path / ".d.npz.123.tmp").write_bytes(b"partial")
    paths = list_scenarios(tmp_path)
    assert [p.name for p in paths] == ["a.npz", "b.npz", "c.npz"]
    bank = load_bank(tmp_path)
    assert [scene.name for scene in bank.scenarios] == ["a", "b", "c"]
    with pytest.raises(FileNotFoundError, match="no scenario files"):
        load_bank(_empty(tmp_path))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        list_scenarios(tmp_path / "missing")


def _empty(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    return empty


def _rewrite(path, **changes) -> None:
    """Rewrite ``path`` with keys replaced (None deletes a key)."""
    with np.load(path) as data:
        arrays = {key: data[key] for key in data.files}
    for key, value in changes.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"schema": np.array("something-else")}, "expected schema 'riskflow-scenario'"),
        ({"schema": None}, "no 'schema' key"),
        ({"version": np.array(2)}, "version 2 is not supported"),
        ({"version": np.array("1")}, "malformed 'version'"),
        ({"valid": None}, r"missing key\(s\) \['valid'\]"),
        ({"map_lane_ids": None, "ego_index": None}, r"missing key\(s\) \['ego_index'"),
        ({"states": np.zeros((3, 40, 3))}, "'states' has shape"),
        ({"valid": np.ones((3, 39), dtype=bool)}, "'valid' has shape"),
        ({"length": np.ones(4)}, "'length' has shape"),
        ({"agent_ids": np.array(["a", "b"])}, "'agent_ids' has shape"),
        ({"map_lane_offsets": np.array([0, 2])}, r"'map_lane_widths' has shape.*L\+1=2, L=2"),
        ({"map_lane_offsets": np.array([0, 6, 5])}, "'lane_offsets' must rise from 0 to 5"),
        ({"map_origin": np.zeros(3)}, "'map_origin' has shape"),
        ({"valid": np.ones((3, 40), dtype=np.int8)}, "'valid' has dtype int8"),
        ({"name": np.array(3)}, "'name' has dtype"),
        ({"ego_index": np.array(7)}, "ego_index must be in"),
        ({"ego_index": np.array(2)}, "ego must be valid at the current step"),
        ({"length": np.array([4.5, -1.0, 2.0])}, "Scenario.length must be finite, > 0"),
        ({"map_drivable": np.zeros((4, 4), dtype=bool)}, "invalid map"),
    ],
)
def test_bad_files_raise_a_clear_error(tmp_path, changes, message):
    path = save_scenario(_scenario(), tmp_path / "scene.npz")
    _rewrite(path, **changes)
    with pytest.raises(ScenarioFormatError, match=message) as error:
        load_scenario(path)
    assert str(path) in str(error.value)
    assert isinstance(error.value, ValueError)


def test_nan_at_a_valid_step_is_an_error_but_not_at_an_invalid_one(tmp_path):
    path = save_scenario(_scenario(), tmp_path / "scene.npz")
    with np.load(path) as data:
        states = data["states"].copy()
    states[2, 0] = np.nan  # agent 2 is invalid at step 0
    _rewrite(path, states=states)
    assert load_scenario(path).num_agents == 3
    states[1, 5, 2] = np.inf
    _rewrite(path, states=states)
    with pytest.raises(ScenarioFormatError, match="NaN or inf at 1 valid step.*agent 1, step 5"):
        load_scenario(path)


def test_unreadable_and_missing_files(tmp_path):
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip at all")
    with pytest.raises(ScenarioFormatError, match="not a readable .npz file"):
        load_scenario(garbage)
    truncated = tmp_path / "truncated.npz"
    full = save_scenario(_scenario(), tmp_path / "full.npz").read_bytes()
    truncated.write_bytes(full[: len(full) // 2])
    with pytest.raises(ScenarioFormatError, match=str(truncated)):
        load_scenario(truncated)
    with pytest.raises(FileNotFoundError, match="not found"):
        load_scenario(tmp_path / "absent.npz")


def test_missing_or_altered_map_file(tmp_path):
    save_scenario(_scenario(), tmp_path / "scene.npz", map_dir=tmp_path / "maps")
    (map_path,) = (tmp_path / "maps").glob("*.npz")
    other = save_scenario(_scenario(drivable_map=_map(shift=9.0)), tmp_path / "o.npz")
    with np.load(other) as data:
        arrays = {k[4:]: data[k] for k in data.files if k.startswith("map_")}
    with zipfile.ZipFile(map_path) as archive:
        header = {k: np.load(archive.open(f"{k}.npy")) for k in ("schema", "version")}
    map_path.unlink()
    with pytest.raises(FileNotFoundError, match="map file"):
        load_map(map_path)
    with open(map_path, "wb") as handle:
        np.savez(handle, **header, **arrays)
    with pytest.raises(ScenarioFormatError, match="differs from the referenced"):
        load_map(map_path, expected_hash="0123456789abcdef")


def test_paths_and_scenes_that_cannot_be_written_or_read(tmp_path):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match="path: .*afile exists and is not a folder"):
        save_scenario(_scenario(), tmp_path / "afile" / "s.npz")
    with pytest.raises(ValueError, match="is a folder, not a file"):
        save_scenario(_scenario(), tmp_path)
    with pytest.raises(TypeError, match="scenario must be a Scenario, got str"):
        save_scenario("scene", tmp_path / "s.npz")
    for path in (123, None):
        with pytest.raises(ValueError, match="path must be a file path"):
            load_scenario(path)


def test_pickle_points_to_load_scenarionet(tmp_path):
    path = tmp_path / "scene.pkl"
    path.write_bytes(b"\x80\x04N.")
    with pytest.raises(ScenarioFormatError, match="load_scenarionet"):
        load_scenario(path)


def test_bank_errors_name_the_expected_format(tmp_path):
    pickled = tmp_path / "scene.pkl"
    pickled.write_bytes(b"\x80\x04N.")
    with pytest.raises(NotADirectoryError, match=r"is a file.*load_scenarionet"):
        load_bank(pickled)
    with pytest.raises(FileNotFoundError, match=r"ScenarioNet pickles.*load_scenarionet"):
        load_bank(tmp_path)
