"""ScenarioNet export: the project's own loader reads an exported scene or rollout back to
the same tracks and map; the description keeps MetaDrive's sanity-check rules."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import shapely

from policies.harness import ClosedLoop
from policies.planners import IDMPlanner
from riskflow_env.agents.idm import IDMPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.dynamics import wrap_angle
from riskflow_env.scenarios import save_scenario, shipped_bank
from riskflow_env.scenarios.exchange import export_scenario
from riskflow_env.scenarios.logged_surface import GROW, logged_boxes
from riskflow_env.scenarios.scenarionet import load_scenarionet
from riskflow_env.scenarios.scenarionet_export import DESCRIPTION_VERSION, to_description
from tests.samples import SAMPLES

FLOAT32 = np.finfo(np.float32).eps  # the description's tracks are float32
FIRST_LEVEL = {
    "id",
    "version",
    "length",
    "tracks",
    "dynamic_map_states",
    "map_features",
    "metadata",
}


def one_per_family():
    scenes = {}
    for scene in shipped_bank("eval").scenarios:
        scenes.setdefault(scene.family, scene)
    return list(scenes.values())


def read_back(scene, path):
    (written,) = export_scenario(scene, path, "scenarionet")
    assert written.suffix == ".pkl"
    return load_scenarionet(
        written,
        resolution=scene.map.resolution,
        current_index=scene.current_index,
        min_future_steps=0,
        crop=False,
    )


def assert_same_tracks(scene, back):
    ids = list(scene.agent_ids) or [str(row) for row in range(scene.num_agents)]
    rows = [ids.index(agent) for agent in back.agent_ids]
    assert rows[0] == scene.ego_index and sorted(rows) == list(range(scene.num_agents))
    valid = scene.valid[rows]
    np.testing.assert_array_equal(back.valid, valid)
    states, again = scene.states[rows][valid], back.states[valid]
    scale = np.abs(states).max(axis=0) + 1.0
    tolerance = 4 * FLOAT32 * scale
    assert np.all(np.abs(again[:, :3] - states[:, :3]) <= tolerance[:3])
    assert np.all(np.abs(wrap_angle(again[:, 3] - states[:, 3])) <= tolerance[3])
    np.testing.assert_allclose(back.length, scene.length[rows], rtol=FLOAT32)
    np.testing.assert_allclose(back.width, scene.width[rows], rtol=FLOAT32)
    assert back.states.shape == scene.states.shape


def assert_logged_ground(scene, pixels):
    """The (H, W) ``pixels`` of ``scene.map`` lie under the scene's logged vehicles (the
    loader adds the ground they stand on where a box reaches within
    ``logged_surface.GROW`` of the road's edge: riskflow_env.scenarios.logged_surface)
    or on the road's edge (the added ground moves the raster's origin, and the edge is
    sampled anew)."""
    boxes = logged_boxes(
        scene.states[..., :2], scene.states[..., 3], scene.valid, scene.length, scene.width
    )
    ground = shapely.union_all(boxes.polygons(GROW + scene.map.resolution))
    rows, cols = np.nonzero(pixels)
    origin, resolution = scene.map.origin, scene.map.resolution
    centres = np.stack([cols + 0.5, rows + 0.5], axis=1) * resolution + origin
    under = shapely.contains_xy(ground, centres[:, 0], centres[:, 1])
    edge = np.abs(scene.map.sdf_at(centres)) <= resolution
    assert np.all(under | edge)


def drivable_at_pixel_centres(original, loaded):
    """(H, W) bool: ``loaded``'s drivable flag at the centres of ``original``'s pixels."""
    height, width = original.shape
    x = original.origin[0] + (np.arange(width) + 0.5) * original.resolution
    y = original.origin[1] + (np.arange(height) + 0.5) * original.resolution
    return loaded.is_drivable(np.stack(np.meshgrid(x, y), axis=-1))


@pytest.mark.parametrize("scene", one_per_family(), ids=lambda scene: scene.family)
def test_a_shipped_scene_reads_back_to_the_same_tracks_and_map(scene, tmp_path):
    back = read_back(scene, tmp_path / "scene")
    assert_same_tracks(scene, back)
    again = drivable_at_pixel_centres(scene.map, back.map)
    assert_logged_ground(scene, again != scene.map.drivable)
    assert [lane.lane_id for lane in back.map.lanes] == [lane.lane_id for lane in scene.map.lanes]
    for lane, again in zip(scene.map.lanes, back.map.lanes, strict=True):
        np.testing.assert_array_equal(again.centerline, lane.centerline)
        assert again.width == pytest.approx(lane.width)
        assert again.successors == lane.successors
        assert again.speed_limit == pytest.approx(lane.speed_limit)


def test_a_rollout_reads_back_to_its_executed_tracks(tmp_path):
    scene = shipped_bank("eval")[2]  # a roundabout
    with ClosedLoop(IDMPlanner(), IDMPolicy(), config=EnvConfig(episode_steps=30)) as loop:
        record = loop.run(scene, seed=0)
    executed = record.to_scenario()
    back = read_back(executed, tmp_path / "rollout")
    assert_same_tracks(executed, back)
    present = np.flatnonzero(record.present)
    steps = record.states.shape[1]
    now = executed.current_index
    np.testing.assert_allclose(  # the ego (row 0) and every vehicle, step by step
        back.states[:, now : now + steps, :2], record.states[present, :, :2], atol=1e-3
    )


def test_the_description_keeps_metadrive_sanity_rules():
    scene = shipped_bank("eval")[0]
    description = to_description(scene)
    assert set(description) == FIRST_LEVEL
    assert description["version"] == DESCRIPTION_VERSION
    steps = description["length"]
    metadata = description["metadata"]
    assert {"metadrive_processed", "coordinate", "ts", "sdc_id"} <= set(metadata)
    assert metadata["ts"].shape == (steps,)
    assert metadata["sdc_id"] in description["tracks"]
    dtypes = {
        "position": (3, np.float32),
        "heading": (None, np.float32),
        "velocity": (2, np.float32),
        "valid": (None, np.bool_),
        "length": (1, np.float32),
        "width": (1, np.float32),
        "height": (1, np.float32),
    }
    for track_id, track in description["tracks"].items():
        assert track["type"] == "VEHICLE" and track["metadata"]["object_id"] == track_id
        state = track["state"]
        for key, (columns, dtype) in dtypes.items():
            shape = (steps,) if columns is None else (steps, columns)
            assert state[key].shape == shape and state[key].dtype == dtype, key
        invalid = ~state["valid"]
        for key in dtypes:  # MetaDrive's valid_check: zero where not valid
            assert not np.any(state[key][invalid]), key
    for feature in description["map_features"].values():
        assert feature["polyline"].ndim == 2
    pickle.loads(pickle.dumps(description))  # native containers and arrays only


@pytest.mark.skipif(not SAMPLES, reason="no ScenarioNet samples (tests/samples.py)")
def test_a_recorded_scene_reads_back_to_its_tracks_and_nearly_its_map(tmp_path):
    """Recorded maps are drawn from lane outlines and drivable-area rings the map does not
    keep: the outline comes back exactly, plus the lanes' own surfaces (centreline +-
    width / 2), on a grid that may shift by a fraction of a pixel."""
    for sample in SAMPLES:
        scene = load_scenarionet(sample)
        back = read_back(scene, tmp_path / sample.stem)
        assert_same_tracks(scene, back)
        differ = drivable_at_pixel_centres(scene.map, back.map) != scene.map.drivable
        assert differ.mean() < 0.03, sample.name  # measured 0.6-1.4 %


def test_bad_arguments_are_named(tmp_path):
    scene = shipped_bank("eval")[0]
    with pytest.raises(ValueError, match="format must be one of"):
        export_scenario(scene, tmp_path / "x", "sumo")
    with pytest.raises(TypeError, match="scenario must be a Scenario"):
        export_scenario("scene.npz", tmp_path / "x", "scenarionet")


def test_riskflow_data_export_writes_every_file(tmp_path, capsys):
    from riskflow_env.scenarios.cli import main

    scene = tmp_path / "scene.npz"
    save_scenario(shipped_bank("eval")[1], scene)
    twice = ["export", str(scene), str(scene), "--format", "scenarionet", "--out", str(tmp_path)]
    assert main(twice) == 0  # a file named twice is converted once
    assert "wrote 1 file(s)" in capsys.readouterr().out
    back = load_scenarionet(tmp_path / "scene.pkl", min_future_steps=0, crop=False)
    with pytest.raises(ValueError, match="for a RiskFlow .npz scene use .*load_scenario"):
        load_scenarionet(scene)
    assert back.num_agents == shipped_bank("eval")[1].num_agents
    with pytest.raises(SystemExit):
        main(["export", str(tmp_path / "none.npz"), "--format", "scenarionet", "--out", "x"])
    assert "error: no such scene file" in capsys.readouterr().err


def test_export_of_commonroad_without_the_extra_is_one_line(tmp_path, capsys, monkeypatch):
    """A CommonRoad input without commonroad-io: one line naming the file, exit 2."""
    from riskflow_env.scenarios import commonroad_import
    from riskflow_env.scenarios.cli import main

    def missing():
        raise ImportError("CommonRoad files need commonroad-io")

    monkeypatch.setattr(commonroad_import, "commonroad_io", missing)
    xml = tmp_path / "scene.xml"
    xml.write_text('<?xml version="1.0"?><commonRoad></commonRoad>')
    with pytest.raises(SystemExit) as exit_info:
        main(["export", str(xml), "--format", "scenarionet", "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert f"error: {xml} is a CommonRoad scenario: CommonRoad files need" in error


def test_export_names_keep_dotted_stems_and_never_overwrite_an_input(tmp_path):
    from riskflow_env.scenarios.exchange import export_files, output_path

    assert output_path("out/sd_v1.0-mini_scene-0061", "scenarionet").name == (
        "sd_v1.0-mini_scene-0061.pkl"
    )
    assert output_path("failures/a-seed0.npz", "commonroad").name == "a-seed0.xml"
    scenes = [tmp_path / "sd_v1.0-a.npz", tmp_path / "sd_v1.0-b.npz"]
    for path, scene in zip(scenes, shipped_bank("eval")[:2], strict=True):
        save_scenario(scene, path)
    written = export_files(scenes, ("scenarionet",), tmp_path / "out")
    assert sorted(p.name for p in written) == ["sd_v1.0-a.pkl", "sd_v1.0-b.pkl"]
    pickled = tmp_path / "scene.pkl"
    written[0].rename(pickled)
    with pytest.raises(ValueError, match="would overwrite"):
        export_files([pickled], ("scenarionet",), tmp_path)
    (tmp_path / "other").mkdir()
    twin = tmp_path / "other" / "sd_v1.0-a.npz"
    save_scenario(shipped_bank("eval")[0], twin)
    with pytest.raises(ValueError, match="would both be exported"):
        export_files([scenes[0], twin], ("scenarionet",), tmp_path / "out")
