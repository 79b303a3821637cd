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
    assert "batched scenes/s" in out and "ratio" in out


def test_strive_and_a_bad_method(capsys):
    bench = _module()
    argv = ["--scenes", "2", "--rounds", "1", "--calls", "1", "--guidance-steps", "2"]
    rows = bench.main([*argv, "--method", "strive"])
    assert rows[0]["batched"] > 0 and rows[0]["loop"] > 0
    assert "StriveAdversary, K = 5" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="--method"):
        bench.main([*argv, "--method", "ddpm"])


def test_a_diffusion_baseline(capsys):
    bench = _module()
    argv = ["--scenes", "2", "--rounds", "1", "--calls", "1", "--diffusion-steps", "2"]
    rows = bench.main([*argv, "--method", "ctgpp"])
    assert rows[0]["batched"] > 0 and rows[0]["loop"] > 0
    assert {"denoising", "guidance"} <= set(rows[0]["phases"])
    assert "DiffusionAdversary, K = 5, ctgpp, 2 denoising levels" in capsys.readouterr().out
