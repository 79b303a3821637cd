"""Shared by the hostile-file tests of the loaders (test_hostile_pickles2.py,
test_hostile_scenarionet.py): a small file written in the test, read in a capped child
process (:mod:`tests.capped`), refused with a short message naming what it must, or
loaded, within the CPU-time and memory bounds."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from tests.capped import Outcome, assert_bounded, run_capped

SETUP = (
    "from riskflow_env.scenarios.safe_pickle import load_data_pickle\n"
    "from riskflow_env.scenarios.scenarionet import load_scenarionet\n"
    "from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset"
)


def refused(outcome: Outcome, *fragments: str, error: str = "ValueError") -> None:
    """``error`` whose short message holds every fragment, within a CPU-time bound and 500 MB."""
    assert outcome.error == error, outcome
    assert outcome.chars < 1000, outcome
    for fragment in fragments:
        assert fragment in outcome.message, (fragment, outcome.message)
    assert_bounded(outcome)


def loaded(outcome: Outcome) -> None:
    assert outcome.error is None, outcome
    assert_bounded(outcome)


def run(path: Path, loader: str = "load_data_pickle", args: str = "", tail: str = "") -> Outcome:
    return run_capped(SETUP, f"{loader}({str(path)!r}{args}){tail}")


def write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    assert path.stat().st_size < 2 * 2**20
    return path


# -- ScenarioNet scene descriptions ---------------------------------------------------------


def vehicle_track(steps: int = 91, x: float = 0.0, y: float = 0.0) -> dict:
    t = np.arange(steps) * 0.1
    state = {
        "position": np.stack([x + 10 * t, np.full(steps, y), np.zeros(steps)], axis=1),
        "heading": np.zeros(steps),
        "velocity": np.tile([10.0, 0.0], (steps, 1)),
        "valid": np.ones(steps, dtype=bool),
        "length": np.full((steps, 1), 4.5),
        "width": np.full((steps, 1), 2.0),
    }
    return {"type": "VEHICLE", "state": state}


def lane_feature(points: np.ndarray, **extra: object) -> dict:
    return {"type": "LANE_SURFACE_STREET", "polyline": np.asarray(points, float), **extra}


def scene_description(tracks: dict | None = None, features: dict | None = None, **metadata) -> dict:
    """A valid scene: the SDC drives 90 m along one straight lane."""
    tracks = {"ego": vehicle_track()} if tracks is None else tracks
    road = {"road": lane_feature([[-50.0, 0.0], [150.0, 0.0]], width=np.array([3.5, 3.5]))}
    meta = {"sdc_id": "ego", "sample_rate": 0.1, "scenario_id": "hostile", **metadata}
    return {
        "id": "hostile",
        "tracks": tracks,
        "map_features": {**road, **(features or {})},
        "metadata": meta,
    }


def scene_file(tmp_path: Path, name: str, description: dict) -> Path:
    return write(tmp_path, name, pickle.dumps(description, protocol=4))
