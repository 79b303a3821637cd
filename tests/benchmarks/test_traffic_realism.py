"""benchmarks/traffic_realism.py end to end on one scene and a short episode."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from riskflow_env.metrics import RolloutRecord
from tests.benchmarks.scripts import load_benchmark


def _module():
    return load_benchmark("traffic_realism")


def test_one_scene_rows_with_every_column(tmp_path, capsys):
    bench = _module()
    out = tmp_path / "realism.json"
    rows = bench.main(["--scenes", "1", "--duration", "1.0", "--out", str(out)])
    assert [row["label"] for row in rows] == ["bits", "idm", "replay"]
    keys = {key for key, _, _ in bench.COLUMNS} | {"jerk_p95_by_phase", "rollouts", "vehicles"}
    for row in rows:
        assert keys <= set(row)
        assert row["rollouts"] == 1 and len(row["jerk_p95_by_phase"]) == 5
        assert 0.0 <= row["veh_coll"] <= 1.0 and 0.0 <= row["orr_fp"] <= 1.0
        assert row["log_veh_coll"] == 0.0  # the shipped bank's recorded boxes never overlap
        assert np.isfinite(row["jerk_p95"]) and np.isfinite(row["wosac"])
    written = json.loads(out.read_text())
    assert written["rows"][0]["label"] == "bits"
    assert written["config"]["methods"] == ["bits", "idm", "replay"]
    assert "| bits |" in capsys.readouterr().out


def test_scene_choice_covers_every_family():
    bench = _module()

    class Scene:
        def __init__(self, family):
            self.family = family

    scenes = [Scene(f) for f in "aaabbbc"]
    assert bench.pick_scenes(scenes, 3) == [0, 3, 6]
    assert bench.pick_scenes(scenes, 5) == [0, 1, 3, 4, 6]


def test_raw_and_checkpoint_rows(capsys):
    """--raw puts bits-raw next to bits; --checkpoint makes both rows per file, named by it."""
    bench = _module()
    shipped = Path(bench.__file__).resolve().parents[1] / "policies/checkpoints/riskflow_default.pt"
    argv = ["--scenes", "1", "--duration", "0.5", "--baselines", "replay", "--raw"]
    rows = bench.main([*argv, "--checkpoint", str(shipped)])
    labels = ["bits riskflow_default.pt", "bits-raw riskflow_default.pt", "replay"]
    assert [row["label"] for row in rows] == labels
    assert "| bits-raw riskflow_default.pt |" in capsys.readouterr().out


def test_log_contacts_count_the_logged_boxes(monkeypatch):
    """log_veh_coll counts the vehicles whose logged boxes overlap another's, whatever the
    simulation did: here two of three logged vehicles share a place at one step."""
    bench = _module()
    states = np.zeros((3, 4, 4))
    states[:, :, 0] = np.array([0.0, 20.0, 40.0])[:, None]  # simulated: far apart
    reference = states.copy()
    reference[1, 2, 0] = 1.0  # logged: vehicle 1 on vehicle 0 at step 2
    record = RolloutRecord(
        states=states, valid=np.ones((3, 4), bool), length=np.full(3, 4.0),
        width=np.full(3, 2.0), reference=reference, reference_valid=np.ones((3, 4), bool),
        ego_index=2, evaluated=np.array([True, True, False]),
    )  # fmt: skip
    monkeypatch.setattr(bench, "rollout_episode", lambda job: (None, record, None))
    monkeypatch.setattr(bench, "wosac_scene", lambda records: {"metametric": 0.0})
    row = bench.measure(bench.RealismJob(job=None, label="x", period=5))
    assert (row["involved"], row["log_involved"], row["vehicles"]) == (0, 2, 2)


@pytest.mark.parametrize(
    "argv",
    [
        ["--scenes", "0"],
        ["--duration", "0"],
        ["--checkpoint", "missing.pt"],
        ["--seeds", "-1"],
        ["--seeds", "0", "0"],
    ],
)
def test_bad_options(argv):
    with pytest.raises(SystemExit):
        _module().parse_args(argv)
