"""benchmarks/failures_that_matter.py: a tiny run prints the table and resumes."""

from __future__ import annotations

from tests.benchmarks.scripts import load_benchmark


def test_a_tiny_run_prints_the_table_and_a_rerun_resumes(tmp_path, capsys):
    bench = load_benchmark("failures_that_matter")
    out = tmp_path / "results.jsonl"
    options = bench.Options(
        planners=("idm", "constant_velocity"), scenes=1, seeds=(0, 1), steps=20, out=out
    )
    summaries = bench.main(options)
    assert list(summaries) == ["idm", "constant_velocity"]
    assert summaries["idm"]["episodes"] == 2
    printed = capsys.readouterr().out
    assert "avoidable failures" in printed and "idm - constant_velocity" in printed
    lines = out.read_text().splitlines()
    assert len(lines) == 4
    bench.main(options)  # everything is done: nothing runs again
    assert out.read_text().splitlines() == lines


def test_a_folder_with_fewer_scenes_than_asked_counts_the_scenes_it_has(
    tmp_path, capsys, monkeypatch
):
    bench = load_benchmark("failures_that_matter")
    one_scene = bench.scenes(bench.Options(scenes=1))
    monkeypatch.setattr(bench, "scenes", lambda options: one_scene)
    out = tmp_path / "results.jsonl"
    options = bench.Options(
        planners=("constant_velocity",), scenes=100, seeds=(0, 1), steps=10, out=out
    )
    assert bench.main(options)["constant_velocity"]["episodes"] == 2
    assert "2 episodes per planner" in capsys.readouterr().out


def test_a_results_file_of_other_settings_is_not_resumed(tmp_path):
    """A rerun with another episode length or K reported the old episodes as its own."""
    import dataclasses

    import pytest

    bench = load_benchmark("failures_that_matter")
    out = tmp_path / "results.jsonl"
    options = bench.Options(planners=("constant_velocity",), scenes=1, steps=10, out=out)
    bench.main(options)
    for changes in ({"steps": 20}, {"k": 0}, {"target": "others"}):
        with pytest.raises(ValueError, match="holds episodes of other settings"):
            bench.main(dataclasses.replace(options, **changes))
    assert len(out.read_text().splitlines()) == 1
    bench.main(dataclasses.replace(options, steps=20, fresh=True))  # --fresh starts over
    assert '"steps": 20' in out.read_text()
    with pytest.raises(ValueError, match="--scenes 500: the shipped evaluation bank holds"):
        bench.scenes(bench.Options(scenes=500))


def test_k_is_an_int_or_all():
    """``--k all`` guides every vehicle (the other scripts take it); a bad value names --k."""
    import pytest

    bench = load_benchmark("failures_that_matter")
    assert bench.Options(k="all").k == "all" and bench.Options(k="3").k == 3
    assert bench.Options(k=3).settings()["k"] == 3  # the rows of earlier runs still resume
    for bad in ("-1", "x", "2.5"):
        with pytest.raises(ValueError, match="--k: expected an int >= 0 or 'all'"):
            bench.Options(k=bad)
