"""benchmarks/step_throughput.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark

TINY = ["--seconds", "0.05", "--rounds", "1", "--batch-agents", "4", "--batch-scenes", "2"]
TINY += ["--no-startup"]


def test_prints_both_tables(capsys):
    bench = load_benchmark("step_throughput")
    results = bench.main([*TINY, "--vehicles", "8"])
    assert [(row["vehicles"], row["path"]) for row in results["api"]] == [
        (8, "compiled"),
        (8, "reference"),
    ]
    assert all(row["highway"] > 0 and row["riskflow"] > 0 for row in results["api"])
    assert [row["observations"] for row in results["batched"]] == [True, True, False, False]
    assert results["startup"] == []
    out = capsys.readouterr().out
    assert "highway-env vehicle-steps/s" in out and "numpy float64" in out
    assert "compiled agent-steps/s | reference agent-steps/s" in out
    assert "What limits 8 vehicles on the compiled path" in out and "% " in out


def test_startup_is_measured_in_fresh_processes(capsys):
    bench = load_benchmark("step_throughput")
    if bench.compiled.kernels() is None:
        pytest.skip("numba is not installed")
    results = bench.main([*TINY[:-1], "--no-api", "--paths", "compiled"])
    (startup,) = results["startup"]
    assert startup["compile"] > startup["load"] > 0 and startup["import"] >= 0
    assert "kernel cache" in capsys.readouterr().out


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
        (["--paths", "jit"], "--paths"),
    ],
)
def test_bad_options_name_the_flag(flags, message):
    bench = load_benchmark("step_throughput")
    with pytest.raises(SystemExit, match=message):
        bench.main([*TINY, "--no-api", *flags])
