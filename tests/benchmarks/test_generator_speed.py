"""benchmarks/generator_speed.py end to end at its smallest size."""

from __future__ import annotations

from tests.benchmarks.scripts import load_benchmark


def test_prints_the_latency_and_training_rows(capsys):
    bench = load_benchmark("generator_speed")
    argv = ["--repeats", "1", "--warmup", "0", "--threads", "1", "--agents", "4"]
    rows = bench.main([*argv, "--train-scenes", "2", "--train-agents", "4"])
    assert len(rows) == 3 and all(ms > 0 for ms in rows.values())
    out = capsys.readouterr().out
    assert "forward, 1 scene x 4 agents" in out and "JVP / flow-matching step time" in out
