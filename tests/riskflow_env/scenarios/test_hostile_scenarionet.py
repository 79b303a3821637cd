"""Hostile ScenarioNet scenes and dataset folders, and map rasterisation: small files
whose counts, shared references or geometry would buy unbounded time or memory are
refused before anything is built (or load), within a CPU-time bound and 500 MB; error
messages stay short whatever the file holds. Built here, read in a capped child process
(:mod:`tests.riskflow_env.scenarios.hostile_files`)."""

from __future__ import annotations

import pickle
import time
from pathlib import Path

import numpy as np
import pytest
import shapely

from tests.riskflow_env.scenarios.hostile_files import (
    lane_feature,
    loaded,
    refused,
    run,
    scene_description,
    scene_file,
    vehicle_track,
)

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md


# -- ScenarioNet scenarios -----------------------------------------------------------------


def _star(vertices: int, radius: float = 40.0, centre: float = 50.0) -> np.ndarray:
    """A closed star polygon: every edge crosses about ``vertices / 2`` others."""
    angle = 2 * np.pi * (np.arange(vertices) * (vertices // 2) % vertices) / vertices
    return np.stack([centre + radius * np.cos(angle), radius * np.sin(angle)], axis=1)


RING = np.array([[0, -5], [9, -5], [9, 5], [0, 5], [0, -5]], dtype=float)  # closed
SHORT = [[10.0, 1.0], [90.0, 1.0]]


def test_valid_scene_loads(tmp_path):
    loaded(run(scene_file(tmp_path, "valid.pkl", scene_description()), "load_scenarionet"))


@pytest.mark.parametrize(
    ("name", "description", "fragment"),
    [
        # one track shared 20,000 times (1,000,000 x 91 steps made 5.6 GB and 102 s)
        (
            "tracks",
            scene_description(
                dict.fromkeys(["ego"] + [f"v{i}" for i in range(20_000)], vehicle_track())
            ),
            "MAX_TRACKS",
        ),
        (
            "track_steps",
            scene_description(
                dict.fromkeys(["ego"] + [f"v{i}" for i in range(9000)], vehicle_track(200))
            ),
            "MAX_TRACK_STEPS",
        ),
        # one 50,000-point polyline shared by 2,000 lanes (4.0 GB): past what the pickle
        # may expand to; one of 1,600 points: past the map's points
        (
            "polylines",
            scene_description(
                features=dict.fromkeys(
                    (f"l{i}" for i in range(2000)), lane_feature(np.zeros((50_000, 2)) + [0, 1])
                )
            ),
            "MAX_ELEMENTS",
        ),
        (
            "polylines_1600",
            scene_description(
                features=dict.fromkeys(
                    (f"l{i}" for i in range(2000)), lane_feature(np.zeros((1600, 2)) + [0, 1])
                )
            ),
            "MAX_MAP_POINTS",
        ),
        (
            "feature_points",
            scene_description(features={"big": lane_feature(np.zeros((50_000, 2)))}),
            "MAX_FEATURE_POINTS",
        ),
        (
            "exit_lanes",
            scene_description(features={"l": lane_feature(SHORT, exit_lanes=["x"] * 10**5)}),
            "MAX_EXIT_LANES",
        ),
        (
            "star_polygon",
            scene_description(features={"s": lane_feature(SHORT, polygon=_star(501))}),
            "MAX_REPAIR_CROSSINGS",
        ),
        (
            "star_centreline",
            scene_description(features={"s": lane_feature(_star(101)[:-1])}),
            "MAX_REPAIR_CROSSINGS",
        ),
        (
            "rings",
            scene_description(
                features={
                    f"boundary_{i}": {
                        "type": "ROAD_LINE_SOLID_SINGLE_WHITE",
                        "polyline": RING + i % 50,
                    }
                    for i in range(300)
                }
            ),
            "MAX_BOUNDARY_RINGS",
        ),
        ("sdc_id_digits", scene_description(sdc_id=10**5000), "metadata['sdc_id'] must be an id"),
        ("ts_rows", scene_description(ts=[[0.0] * 100_000] * 91), "MAX_STEPS"),
    ],
)
def test_scenarionet_counts_refused_before_building(tmp_path, name, description, fragment):
    path = scene_file(tmp_path, f"{name}.pkl", description)
    refused(run(path, "load_scenarionet"), f"{name}.pkl", fragment)


def test_scenarionet_map_area_refused(tmp_path):
    """Vehicles 5 km apart: the cropped map would be 10,000 x 10,000 px (MAX_MAP_PIXELS)."""
    far = vehicle_track(x=5000.0, y=5000.0)
    description = scene_description(
        {"ego": vehicle_track(), "far": far},
        {"far": lane_feature([[4950.0, 5000.0], [5150.0, 5000.0]])},
    )
    path = scene_file(tmp_path, "far.pkl", description)
    refused(run(path, "load_scenarionet"), "far.pkl", "MAX_MAP_PIXELS")


def test_crossing_lanes_load_without_a_union(tmp_path):
    """300 x 300 thin lanes crossing as a grid: their union took 10 s and 490 MB (1,000 x
    1,000: minutes); the map is filled from the lanes' outlines without one (0.1 s)."""
    lanes, width = {}, np.array([0.05, 0.05])
    for i in range(300):
        y, x = -50 + i / 3, -50 + 2 * i / 3
        lanes[f"h{i}"] = lane_feature([[-60, y], [160, y]], width=width)
        lanes[f"v{i}"] = lane_feature([[x, -60], [x, 60]], width=width)
    path = scene_file(tmp_path, "grid.pkl", scene_description(features=lanes))
    loaded(run(path, "load_scenarionet"))


def test_road_edge_grid_refused(tmp_path):
    """A map without lanes is built from the faces of its road edges: 1,000 x 1,000 crossing
    edges took 16 s and 1.2 GB before failing (MAX_EDGE_SEGMENTS, MAX_EDGE_CROSSINGS)."""
    description = scene_description()
    edges = {}
    for i in range(1000):
        y, x = -50 + 0.1 * i, -50 + 0.2 * i
        edges[f"h{i}"] = {"type": "ROAD_EDGE_BOUNDARY", "polyline": np.array([[-60, y], [160, y]])}
        edges[f"v{i}"] = {"type": "ROAD_EDGE_BOUNDARY", "polyline": np.array([[x, -60], [x, 60]])}
    description["map_features"] = edges
    path = scene_file(tmp_path, "edges.pkl", description)
    refused(run(path, "load_scenarionet"), "edges.pkl", "MAX_EDGE_SEGMENTS")
    few = dict(list(edges.items())[:200])  # 100 x 100: 10,000 crossings, read
    path = scene_file(tmp_path, "few_edges.pkl", {**description, "map_features": few})
    loaded(run(path, "load_scenarionet"))


def test_8000_lanes_without_successors_load(tmp_path):
    """A 262 KB file of lanes without ``exit_lanes`` built an L x L matrix (3 GB): 8,000
    lanes on a 100 x 80 grid (the whole map, 500 x 320 m) load."""
    x, y = np.meshgrid(np.arange(100) * 5.0 - 50, np.arange(80) * 4.0 - 160)
    starts = np.stack([x.ravel(), y.ravel()], axis=1)
    width = np.array([2.0, 2.0])
    lanes = {f"l{i}": lane_feature([s, s + [3.0, 0.0]], width=width) for i, s in enumerate(starts)}
    path = scene_file(tmp_path, "lanes.pkl", scene_description(features=lanes))
    assert path.stat().st_size < 2**20
    outcome = run(path, "load_scenarionet", ", crop=False", tail=".map.lanes")
    loaded(outcome)


def test_type_and_id_repr_bombs_are_not_formatted(tmp_path):
    """A track type, an sdc_id and a map feature type that are one list shared at 23 levels
    (repr: 2**23 items, 50 MB) are never formatted: skipped, or quoted by their type."""
    nest: list = []
    for _ in range(23):
        nest = [nest, nest]
    tracks = {"ego": vehicle_track(), "odd": {"type": nest, "state": {}}}
    path = scene_file(
        tmp_path, "types.pkl", scene_description(tracks, {"odd": {"type": nest}}, sdc_id=nest)
    )
    refused(run(path, "load_scenarionet"), "types.pkl", "got a list of 2 items")


# -- ScenarioNet dataset folders -----------------------------------------------------------


OFF = ", map_cache=False"


def _dataset(folder: Path, summary: dict, scenes: dict[str, bytes] | None = None) -> Path:
    folder.mkdir()
    (folder / "dataset_summary.pkl").write_bytes(pickle.dumps(summary, protocol=4))
    for name, data in (scenes or {}).items():
        (folder / name).write_bytes(data)
    return folder


def test_summary_sharing_one_huge_metadata_refused(tmp_path):
    """200 entries sharing one metadata dict of 100,000 keys (its copy per entry: 4 GB at
    2,000 x 1,000,000 through riskflow-eval --data)."""
    metadata = {f"k{i}": i for i in range(100_000)}
    folder = _dataset(tmp_path / "data", {f"sd_{i}.pkl": metadata for i in range(200)})
    refused(run(folder, "ScenarioNetDataset", OFF), "dataset_summary.pkl", "MAX_METADATA_KEYS")


def test_summary_entry_with_a_5000_digit_id_names_the_entry(tmp_path):
    folder = _dataset(tmp_path / "data", {"sd_a.pkl": {"scenario_id": 10**5000}})
    refused(run(folder, "ScenarioNetDataset", OFF), "dataset_summary.pkl", "entry sd_a.pkl")


def test_summary_with_a_huge_entry_name_is_quoted_short(tmp_path):
    folder = _dataset(tmp_path / "data", {"x" * 10**6: {}})
    refused(run(folder, "ScenarioNetDataset", OFF), "dataset_summary.pkl", "characters) is not")


def test_unreadable_listed_file_names_it(tmp_path, monkeypatch):
    """An unreadable scene file (a PermissionError when opened) is a ValueError naming the
    file and the summary that lists it."""
    from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset

    data = pickle.dumps(scene_description(), protocol=4)
    folder = _dataset(tmp_path / "data", {"sd_a.pkl": {}}, {"sd_a.pkl": data})
    real_open = Path.open

    def deny(self, *args, **kwargs):
        if self.name == "sd_a.pkl":
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)

    monkeypatch.setattr(Path, "open", deny)
    with pytest.raises(ValueError, match=r"sd_a\.pkl: listed in .*dataset_summary\.pkl.*denied"):
        ScenarioNetDataset(folder, map_cache=False).load(0)


# -- rasterisation -------------------------------------------------------------------------


def test_star_polygon_rasterisation_refused_fast():
    """A 501-vertex star did not finish rasterising in 300 s (its repair: hours)."""
    from riskflow_env.maps import from_polygons
    from riskflow_env.maps.rasterize import grid_for_bounds, rasterize

    star = shapely.Polygon(_star(501))
    start = time.perf_counter()
    with pytest.raises(ValueError, match="MAX_REPAIR_CROSSINGS"):
        from_polygons([star, shapely.box(0, 0, 1, 1)])
    origin, shape = grid_for_bounds(star.bounds, 0.5, 1.0)
    with pytest.raises(ValueError, match="MAX_REPAIR_CROSSINGS"):
        rasterize(star, origin, shape, 0.5)
    assert time.perf_counter() - start < 5.0
    bowtie = shapely.Polygon([(0, 0), (4, 4), (4, 0), (0, 4)])  # one crossing: repaired
    assert from_polygons([bowtie], resolution=0.5).drivable.any()
