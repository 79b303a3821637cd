"""benchmarks/adversary_quality.py: the guided vehicles' off-road share and a tiny run."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from tests.benchmarks.scripts import load_benchmark


def test_guided_footprint_rate_counts_the_guided_vehicles_steps_only():
    """The state after each step counts for the vehicles guided when it was planned;
    steps out of the scene do not count."""
    bench = load_benchmark("adversary_quality")
    offroad = np.array([[0, 0, 0, 0], [0, 1, 1, 0], [0, 0, 0, 1]], dtype=bool)
    in_scene = np.ones((3, 4), dtype=bool)
    in_scene[1, 3] = False  # vehicle "a" left before the last step
    record = SimpleNamespace(
        agent_names=("ego", "a", "b"), offroad_footprint=offroad, in_scene=in_scene
    )
    guided = [("a",), ("a",), ("a", "b")]  # planned before steps 1, 2, 3
    # a: steps 1, 2 (both off road), step 3 out of the scene; b: step 3 (off road)
    assert bench.guided_footprint_rate(record, guided) == 1.0
    assert bench.guided_footprint_rate(record, [(), ("b",), ()]) == 0.0
    assert math.isnan(bench.guided_footprint_rate(record, [(), (), ()]))


def test_a_tiny_run_of_the_default_and_the_raw_generator(tmp_path, capsys):
    """The default riskflow, riskflow-raw next to it with --raw, --set options for both."""
    bench = load_benchmark("adversary_quality")
    argv = ["--scenes", "1", "--ks", "2", "--raw", "--set", "guidance_steps=2"]
    results = bench.main([*argv, "--out", str(tmp_path)])
    assert list(results) == ["K=2", "K=2 raw"]
    assert [results[label]["method"] for label in results] == ["riskflow", "riskflow-raw"]
    out = capsys.readouterr().out
    assert "riskflow, riskflow-raw: guidance_steps=2" in out
    assert "| K=2 | K=2 raw | K=2 / K=2 | K=2 raw / K=2 raw |" in out
    assert "agent-steps of guided vehicles, footprint off road" in out
    assert (tmp_path / "quality.json").stat().st_size > 0


def test_bad_options_name_the_flag(capsys):
    bench = load_benchmark("adversary_quality")
    cases = (
        (["--ks", "5,-1"], "--k"),
        (["--set", "nope=1"], "--set"),
        (["--scenes", "500"], "--scenes 500: the shipped evaluation bank holds only"),
        (["--ks", "5,5"], "--ks: each K once"),
        (["--out", __file__], "--out: "),
        (["--seed", "-1"], "--seed must be one or more ints in [0, 2**32)"),
        (["--target", "x"], "--target must be one of"),
    )
    for argv, flag in cases:
        with pytest.raises(SystemExit):
            bench.main(argv)
        assert flag in capsys.readouterr().err
