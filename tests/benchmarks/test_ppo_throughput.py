"""benchmarks/ppo_throughput.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

TINY = "--scenes 3 --episode-steps 10 --guidance-steps 1 --n-steps 4 --batch-size 8 --n-epochs 1"


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
        (["--decisions", "0"], "--decisions must be >= 1"),
    ],
)
def test_bad_options_name_the_flag(flags, message, capsys):
    bench = load_benchmark("ppo_throughput")
    with pytest.raises(SystemExit):
        bench.main(flags)
    assert message in capsys.readouterr().err
