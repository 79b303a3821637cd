"""benchmarks/realism_diagnosis.py runs end to end on one scene (no timing assertions)."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark


@pytest.fixture(scope="module")
def diagnosis():
    return load_benchmark("realism_diagnosis")


def test_one_scene_gives_every_table(diagnosis, capsys):
    text = diagnosis.main(["--scenes", "1"])
    headings = ("one-shot plans overlap", "collision starts", "off-road centroid share")
    for heading in (*headings, "centroid past a road's end"):
        assert heading in text
    assert "| highway | 1 |" in text and "| 0-2 |" in text
    assert "1 scenes in" in capsys.readouterr().out


def test_bad_scene_count(diagnosis):
    with pytest.raises(SystemExit):
        diagnosis.main(["--scenes", "0"])


def test_a_bank_of_your_own(diagnosis, tmp_path):
    """--bank reads a scene folder; --scenes beyond its size takes what there is."""
    from riskflow_env.scenarios import shipped_bank
    from riskflow_env.scenarios.io import save_scenario

    scene = shipped_bank("eval")[2]  # a roundabout
    save_scenario(scene, tmp_path / "00000-mine.npz", map_dir=tmp_path / "maps")
    text = diagnosis.main(["--bank", str(tmp_path), "--scenes", "3"])
    assert "| roundabout | 1 |" in text
