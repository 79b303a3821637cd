"""benchmarks/adversary_quality.py: the guided vehicles' off-road share and a tiny run."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

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


def test_a_tiny_run_on_the_realistic_base(tmp_path, capsys):
    bench = load_benchmark("adversary_quality")
    argv = ["--scenes", "1", "--ks", "2,0", "--avoid-steps", "1", "--hold-distance", "2"]
    options = ["--lambda-map", "5", "--step-size", "0.03", "--optimizer", "adam-plan"]
    options += ["--guidance-horizon", "20"]
    bench.main([*argv, *options, "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert "avoid_steps=1, hold_distance=2, lambda_map=5, step_size=0.03, " in out
    assert "optimizer=adam-plan, lambda_sep=100, guidance_horizon=20" in out
    assert "agent-steps of guided vehicles, footprint off road" in out
    assert (tmp_path / "quality.json").stat().st_size > 0
