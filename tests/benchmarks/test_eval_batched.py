"""benchmarks/eval_batched.py end to end at its smallest size (two riskflow-eval processes)."""

from __future__ import annotations

from tests.benchmarks.scripts import load_benchmark


def test_prints_the_per_scene_and_batched_rows(capsys):
    bench = load_benchmark("eval_batched")
    rows = bench.main(["--scenes", "2", "--batch", "2", "--duration", "0.5"])
    assert [row["batch"] for row in rows] == [1, 2]
    assert all(row["rollouts"] == 2 and row["rollout_s"] > 0 for row in rows)
    assert rows[1]["rows"] == 2 and rows[1]["outcome_differs"] == 0
    assert rows[1]["max_diff"] < 1e-4
    out = capsys.readouterr().out
    assert "batch-scenes" in out and "ratio" in out
