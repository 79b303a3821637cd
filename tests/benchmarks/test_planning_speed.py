"""benchmarks/planning_speed.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from policies.learned.plan_avoidance import DEFAULT_AVOID_STEPS
from tests.benchmarks.scripts import load_benchmark


def test_prints_the_phases_and_every_peer(capsys):
    bench = load_benchmark("planning_speed")
    bench.main(
        ["--agents", "6", "--guidance-steps", "2", "--repeats", "1", "--warmup", "0",
         "--avoid-steps", "2"]
    )  # fmt: skip
    out = capsys.readouterr().out
    rows = ("guidance, per step", "unguided generator (K=0)", "re-sampling, best of 2",
            "RiskFlow, 2 avoidance steps", "unguided, 2 avoidance steps", "p10-p90")  # fmt: skip
    assert all(row in out for row in rows), out


def test_the_realistic_base_peers_take_the_default_avoidance_steps():
    bench = load_benchmark("planning_speed")
    assert bench._parse([]).avoid_steps == DEFAULT_AVOID_STEPS
    with pytest.raises(SystemExit):
        bench._parse(["--avoid-steps", "-1"])
