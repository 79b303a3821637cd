"""benchmarks/planning_speed.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark

TINY = ["--agents", "6", "--guidance-steps", "2", "--repeats", "1", "--warmup", "0", "--no-startup"]


def test_prints_the_phases_and_every_peer(capsys):
    bench = load_benchmark("planning_speed")
    medians = bench.main(TINY)
    assert set(medians) == {"riskflow", "bits", "resample", "reference"}
    out = capsys.readouterr().out
    rows = ("the library's default", "guidance, per step", "bits (unguided, K=0)",
            "re-sampling, best of 2", "p10-p90", "planning loops:", "reference loops")  # fmt: skip
    assert all(row in out for row in rows), out
    assert "riskflow-raw" not in out


def test_raw_runs_the_raw_generator_next_to_the_default(capsys):
    bench = load_benchmark("planning_speed")
    medians = bench.main([*TINY, "--raw", "--no-reference"])
    assert set(medians) == {"riskflow", "bits", "resample", "riskflow-raw", "bits-raw"}
    out = capsys.readouterr().out
    assert "riskflow-raw, K=5" in out and "realistic base / raw generator" in out


def test_bad_guidance_steps_name_the_flag():
    bench = load_benchmark("planning_speed")
    with pytest.raises(SystemExit):
        bench._parse(["--guidance-steps", "0"])


@pytest.mark.slow
def test_startup_is_measured_in_fresh_processes():
    """The compiled loops' start-up: compiling into an empty cache costs more than
    loading from the filled one."""
    pytest.importorskip("numba")
    costs = load_benchmark("planning_speed").startup_seconds(6)
    assert set(costs) == {"import", "compile", "load"}
    assert costs["compile"] > costs["load"] and costs["import"] > 0
