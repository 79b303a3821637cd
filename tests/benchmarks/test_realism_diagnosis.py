"""benchmarks/realism_diagnosis.py runs end to end on one scene (no timing assertions)."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark


@pytest.fixture(scope="module")
def diagnosis():
    return load_benchmark("realism_diagnosis")


def test_one_scene_gives_every_table(diagnosis, capsys):
    text = diagnosis.main(["--scenes", "1"])
    assert text.startswith("### bits\n") and "bits-raw" not in text
    headings = ("one-shot plans overlap", "collision starts", "off-road centroid share")
    for heading in (*headings, "centroid past a road's end", "at rest at the start"):
        assert heading in text
    assert "| highway | 1 |" in text and "| 0-2 |" in text
    lateral = text.split("p95 lateral acceleration: generator")[1].splitlines()
    generated, logged = (float(cell) for cell in lateral[2].split("|")[2:4])  # highway
    assert lateral[2].startswith("| highway |") and generated >= 0.0 and logged >= 0.0
    assert "1 scenes in" in capsys.readouterr().out


def test_raw_adds_the_raw_generators_tables(diagnosis):
    text = diagnosis.main(["--scenes", "1", "--raw"])
    default, raw = text.split("### bits-raw\n")
    assert default.startswith("### bits\n")
    assert all("| highway | 1 |" in part and "collision starts" in part for part in (default, raw))


def test_bad_options(diagnosis, capsys):
    with pytest.raises(SystemExit):
        diagnosis.main(["--scenes", "0"])
    with pytest.raises(SystemExit):
        diagnosis.main(["--seed", "-1"])
    assert "--seed must be one or more ints" in capsys.readouterr().err


def test_at_rest_reach_of_a_plan_that_stays_and_one_that_creeps(diagnosis):
    """The plan's and the log's reach of vehicles at rest, nothing for moving ones."""
    import numpy as np

    from riskflow_env.scenarios import shipped_bank

    scene = shipped_bank("eval")[17]  # an intersection with vehicles at rest
    now, rows = scene.current_index, np.arange(scene.num_agents)
    start = scene.states[:, now].copy()
    plans = np.repeat(start[:, None], 10, axis=1)  # 10 steps standing where they are
    plans[:, :, 0] += np.linspace(0.0, 1.5, 10)  # ... every one creeping 1.5 m
    planned = np.ones(scene.num_agents, dtype=bool)
    pairs = diagnosis.at_rest_reach(plans, planned, start, scene, rows)
    at_rest = (start[:, 2] <= 0.2) & scene.valid[:, now : now + 11].all(axis=1)
    assert len(pairs) == at_rest.sum() > 0
    assert all(abs(reach - 1.5) < 1e-9 and log >= 0.0 for reach, log in pairs)


def test_a_bank_of_your_own(diagnosis, tmp_path):
    """--bank reads a scene folder; --scenes beyond its size takes what there is."""
    from riskflow_env.scenarios import shipped_bank
    from riskflow_env.scenarios.io import save_scenario

    scene = shipped_bank("eval")[2]  # a roundabout
    save_scenario(scene, tmp_path / "00000-mine.npz", map_dir=tmp_path / "maps")
    text = diagnosis.main(["--bank", str(tmp_path), "--scenes", "3"])
    assert "| roundabout | 1 |" in text


def test_scenes_without_a_family_are_neither_curved_nor_straight(diagnosis):
    rows = {"highway": [1], diagnosis.NO_FAMILY: [2], "racetrack": [3]}
    groups = diagnosis.grouped(rows)
    assert groups["curved roads"] == [3] and groups["straight roads"] == [1]
    assert sorted(groups["all"]) == [1, 2, 3] and groups[diagnosis.NO_FAMILY] == [2]
