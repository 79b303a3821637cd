"""benchmarks/adversarial_throughput.py end to end at its smallest size."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark


def _module():
    return load_benchmark("adversarial_throughput")


def test_prints_a_row_per_scene_count(capsys):
    bench = _module()
    argv = ["--scenes", "1", "2", "--rounds", "1", "--calls", "1", "--guidance-steps", "2"]
    rows = bench.main(argv)
    assert [row["scenes"] for row in rows] == [1, 2]
    assert all(row["batched"] > 0 and row["loop"] > 0 for row in rows)
    assert {"window", "encoder", "generator", "ranking", "guidance"} <= set(rows[1]["phases"])
    out = capsys.readouterr().out
    assert "riskflow (RiskFlowAdversary), K = 5, K_g = 2" in out
    assert "batched scenes/s" in out and "ratio" in out


@pytest.mark.parametrize("method", ["riskflow-raw", "strive"])
def test_other_adversaries_by_name(method, capsys):
    bench = _module()
    argv = ["--scenes", "2", "--rounds", "1", "--calls", "1", "--guidance-steps", "2"]
    rows = bench.main([*argv, "--method", method])
    assert rows[0]["batched"] > 0 and rows[0]["loop"] > 0
    assert f"{method} (" in capsys.readouterr().out


@pytest.mark.parametrize("method", ["ddpm", "bits", "idm"])
def test_a_method_without_a_controllable_set_is_refused(method):
    with pytest.raises(SystemExit, match="--method must be one of"):
        _module().main(["--scenes", "1", "--method", method])


def test_a_diffusion_baseline(capsys):
    bench = _module()
    argv = ["--scenes", "2", "--rounds", "1", "--calls", "1", "--diffusion-steps", "2"]
    rows = bench.main([*argv, "--method", "ctgpp"])
    assert rows[0]["batched"] > 0 and rows[0]["loop"] > 0
    assert {"denoising", "guidance"} <= set(rows[0]["phases"])
    assert "ctgpp (DiffusionAdversary), K = 5, 2 denoising levels" in capsys.readouterr().out
