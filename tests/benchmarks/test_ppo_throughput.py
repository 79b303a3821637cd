"""benchmarks/ppo_throughput.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

TINY = "--scenes 3 --episode-steps 10 --guidance-steps 1 --n-steps 4 --batch-size 8 --n-epochs 1"


def test_one_row_prints_the_table(capsys):
    """The smoke test: the vector env's row alone, one PPO update of 16 decisions."""
    bench = load_benchmark("ppo_throughput")
    extra = "--scenes 1 --episode-steps 5 --guidance-steps 1 --n-steps 1 --batch-size 16"
    rows = bench.main(["--decisions", "16", "--rows", "vector", "--extra", f"{extra} --n-epochs 1"])
    assert [row["row"] for row in rows] == ["vector"] and rows[0]["fps"] > 0
    out = capsys.readouterr().out
    assert "decisions/s" in out and "ratio = row / vector" in out


@pytest.mark.slow  # two PPO runs, one of them with subprocess envs, one with two shards
def test_prints_the_table(capsys):
    bench = load_benchmark("ppo_throughput")
    rows = bench.main(["--decisions", "64", "--rows", "recipe", "vector-shards2", "--extra", TINY])
    assert [row["row"] for row in rows] == ["recipe", "vector-shards2"]
    assert all(row["fps"] > 0 and row["decisions"] >= 64 for row in rows)
    out = capsys.readouterr().out
    assert "decisions/s" in out and "ratio = row / recipe" in out


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--rows", "nope"], "--rows must be some of"),
        (["--decisions", "0"], "--decisions must be an int >= 1"),
        (["--extra=--vec-env dummy"], "--extra may not set ['--vec-env']"),
        (["--extra", "'a"], "--extra: No closing quotation"),
    ],
)
def test_bad_options_name_the_flag(flags, message, capsys):
    bench = load_benchmark("ppo_throughput")
    with pytest.raises(SystemExit):
        bench.main(flags)
    assert message in capsys.readouterr().err
