"""benchmarks/traffic_realism.py end to end on one scene and a short episode."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.benchmarks.scripts import load_benchmark


def _module():
    return load_benchmark("traffic_realism")


def test_one_scene_rows_with_every_column(tmp_path, capsys):
    bench = _module()
    out = tmp_path / "realism.json"
    rows = bench.main(["--scenes", "1", "--duration", "1.0", "--out", str(out)])
    assert [row["label"] for row in rows] == ["riskflow_default.pt", "idm", "replay"]
    keys = {key for key, _, _ in bench.COLUMNS} | {"jerk_p95_by_phase", "rollouts", "vehicles"}
    for row in rows:
        assert keys <= set(row)
        assert row["rollouts"] == 1 and len(row["jerk_p95_by_phase"]) == 5
        assert 0.0 <= row["veh_coll"] <= 1.0 and 0.0 <= row["orr_fp"] <= 1.0
        assert np.isfinite(row["jerk_p95"]) and np.isfinite(row["wosac"])
    assert json.loads(out.read_text())["rows"][0]["label"] == "riskflow_default.pt"
    assert "| riskflow_default.pt |" in capsys.readouterr().out


def test_scene_choice_covers_every_family():
    bench = _module()

    class Scene:
        def __init__(self, family):
            self.family = family

    scenes = [Scene(f) for f in "aaabbbc"]
    assert bench.pick_scenes(scenes, 3) == [0, 3, 6]
    assert bench.pick_scenes(scenes, 5) == [0, 1, 3, 4, 6]


def test_generator_rows_per_option_value():
    bench = _module()
    # hold, avoidance and blending first always explicit: the rows do not take the
    # policy's defaults (the raw generator unless asked); the blend length is the policy's
    raw = {"hold_distance": 0.0, "avoid_steps": 0, "stitch_first": False}
    assert bench.sampled(1) == raw
    moved = {"base_samples": 8, "hold_distance": 1.5, "avoid_steps": 10}
    assert bench.sampled(8, 1.5, 10) == raw | moved
    assert bench.sampled(1, 0.0, 0, 1, 20, True) == raw | {"stitch_steps": 20, "stitch_first": True}
    assert bench.labelled("g.pt", 1, 0.0) == "g.pt"
    assert bench.labelled("g.pt", 8, 2.0) == "g.pt best of 8 hold 2 m"
    assert bench.labelled("g.pt", 1, 4.0, 10, 1, None, True) == "g.pt hold 4 m avoid 10 first"
    with pytest.raises(SystemExit):
        bench.parse_args(["--hold-distance", "-1"])
