"""benchmarks/ego_env_throughput.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark


def test_prints_a_row_per_scene_count(capsys):
    bench = load_benchmark("ego_env_throughput")
    argv = ["--scenes", "1", "2", "--steps", "2", "--guidance-steps", "2"]
    rows = bench.main(argv)
    assert [row["scenes"] for row in rows] == [1, 2]
    assert all(row["vector"] > 0 and row["loop"] > 0 for row in rows)
    out = capsys.readouterr().out
    assert "vector steps/s" in out and "ratio" in out


def test_the_raw_generator_and_a_method_without_k(capsys):
    bench = load_benchmark("ego_env_throughput")
    rows = bench.main(["--scenes", "1", "--steps", "2", "--method", "riskflow-raw"])
    assert rows[0]["vector"] > 0 and "riskflow-raw adversary" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        bench.main(["--method", "bits"])
