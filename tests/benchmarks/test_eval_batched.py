"""benchmarks/eval_batched.py end to end at its smallest size (two riskflow-eval processes)."""

from __future__ import annotations

import pytest

from tests.benchmarks.scripts import load_benchmark


def test_prints_the_per_scene_and_batched_rows(capsys):
    """The smoke test: one per-scene and one batched riskflow-eval process, the smallest
    run (its rollout time may read 0.0 s: the ratio says n/a, no division by zero)."""
    bench = load_benchmark("eval_batched")
    rows = bench.main(["--scenes", "2", "--batch", "2", "--duration", "0.3"])
    assert [row["batch"] for row in rows] == [1, 2]
    assert all(row["rollouts"] == 2 for row in rows)
    assert rows[1]["rows"] == 2 and rows[1]["outcome_differs"] == 0
    out = capsys.readouterr().out
    assert "batch-scenes" in out and "ratio" in out and "riskflow-eval --methods riskflow" in out


@pytest.mark.slow  # three riskflow-eval processes
def test_perturbed_per_scene_rows(capsys):
    """Per-scene, batched, and the per-scene path with the generator's u0 perturbed
    (``--perturb``): the noise reaches the rollouts (their rows move), rounding does not
    move the batched rows past float tolerance here."""
    bench = load_benchmark("eval_batched")
    argv = ["--scenes", "2", "--batch", "2", "--duration", "0.5", "--perturb", "0.01"]
    rows = bench.main(argv)
    assert [row["batch"] for row in rows] == [1, 2, "1+0.01"]
    assert all(row["rollouts"] == 2 and row["rollout_s"] > 0 for row in rows)
    assert rows[1]["rows"] == 2 and rows[1]["outcome_differs"] == 0
    assert rows[1]["max_diff"] < 1e-4
    assert rows[2]["rows"] == 2 and rows[2]["max_diff"] > 1e-4
    out = capsys.readouterr().out
    assert "batch-scenes" in out and "ratio" in out and "1+0.01" in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--perturb", "0"], "--perturb must be a finite number > 0"),
        (["--perturb", "1e-6", "--workers", "2"], "--perturb needs --workers 1"),
        (["--perturb", "1e-6", "--methods", "ctg"], "--perturb takes MeanFlow methods only"),
    ],
)
def test_perturb_refuses_what_it_cannot_perturb(argv, message):
    bench = load_benchmark("eval_batched")
    with pytest.raises(SystemExit, match=message):
        bench.main(argv)


def test_rows_with_a_number_only_one_run_has_are_apart():
    """A rollout whose ego collides in one run and not in the other has a time to the
    ego's first collision in one row only: counted apart and as an outcome change, the
    largest difference taken over the numbers both rows have (no KeyError)."""
    bench = load_benchmark("eval_batched")
    collided = {"steps": 100, "ego_collision": 1.0, "ade": 2.0,
                "harness": {"time_to_first_ego_collision": 4.5}}  # fmt: skip
    missed = {"steps": 100, "ego_collision": 0.0, "ade": 2.5, "harness": {}}
    same = {"steps": 100, "ego_collision": 0.0, "ade": 1.0, "harness": {}}
    result = bench.compare_rows({"a": collided, "b": same}, {"a": missed, "b": dict(same)})
    assert result == {"max_diff": 1.0, "apart": 1, "outcome_differs": 1, "rows": 2}


@pytest.mark.slow  # two riskflow-eval processes of a diffusion baseline
def test_a_diffusion_baseline_with_fewer_levels(capsys):
    """``--methods ctg --diffusion-steps 2``: the diffusion baseline's chains batched over
    the scenes, and the rows match the per-scene path's."""
    bench = load_benchmark("eval_batched")
    argv = ["--methods", "ctg", "--diffusion-steps", "2", "--scenes", "2", "--batch", "2"]
    rows = bench.main([*argv, "--duration", "0.5"])
    assert [row["batch"] for row in rows] == [1, 2]
    assert rows[1]["rows"] == 2 and rows[1]["outcome_differs"] == 0
    assert rows[1]["max_diff"] < 1e-4
    assert "--diffusion-steps 2" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--batch", "1"], "--batch: distinct values >= 2"),
        (["--batch", "4", "4"], "--batch: distinct values >= 2"),
        (["--out", "FULL"], "is not empty: every timed run starts in a new folder"),
    ],
)
def test_runs_that_would_time_nothing_are_refused(argv, message, tmp_path):
    """A second run into the same --out, or a 'batched' run of one scene, timed the rows of
    an earlier run (0 rollouts, 0.0 s) or repeated the per-scene one."""
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "batch1").mkdir()
    argv = [str(tmp_path / "full") if arg == "FULL" else arg for arg in argv]
    with pytest.raises(SystemExit, match=message):
        load_benchmark("eval_batched").main(["--scenes", "2", *argv])
