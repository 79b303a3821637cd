"""benchmarks/step_throughput.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark

TINY = ["--seconds", "0.05", "--rounds", "1", "--batch-agents", "4", "--batch-scenes", "2"]


def test_prints_both_tables(capsys):
    bench = load_benchmark("step_throughput")
    results = bench.main([*TINY, "--vehicles", "8"])
    assert [row["vehicles"] for row in results["api"]] == [8]
    assert all(row["highway"] > 0 and row["riskflow"] > 0 for row in results["api"])
    assert [row["observations"] for row in results["batched"]] == [True, False]
    out = capsys.readouterr().out
    assert "highway-env vehicle-steps/s" in out and "numpy float64" in out


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_batched_rows_in_float32(backend, capsys):
    bench = load_benchmark("step_throughput")
    results = bench.main([*TINY, "--no-api", "--dtype", "float32", "--backend", backend])
    assert results["api"] == [] and all(row["rate"] > 0 for row in results["batched"])
    where = "numpy" if backend == "numpy" else "torch on cpu"
    assert f"{where} float32" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--backend", "jax"], "--backend"),
        (["--dtype", "float16"], "--dtype"),
        (["--device", "cuda"], "--device cuda needs --backend torch"),
    ],
)
def test_bad_options_name_the_flag(flags, message):
    bench = load_benchmark("step_throughput")
    with pytest.raises(SystemExit, match=message):
        bench.main([*TINY, "--no-api", *flags])
