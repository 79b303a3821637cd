"""The RLlib examples (``policies.rl.rllib``): options, and each script run as a user would
with a tiny budget, one of them sampling in a Ray actor (the ``rllib`` extra)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from policies.rl.rllib import RLlibOptions

ROOT = Path(__file__).resolve().parents[2]
TINY = ("--iterations", "1", "--train-batch", "40", "--minibatch", "20", "--epochs", "1",
        "--episode-steps", "10", "--num-cpus", "2")  # fmt: skip
needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="ray[rllib] is not installed (pip install -e '.[rllib]'; .ci/run installs it)",
)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"iterations": 0}, "--iterations must be an int >= 1, got 0"),
        ({"num_env_runners": -1}, "--num-env-runners must be an int >= 0, got -1"),
        ({"train_batch": 10, "minibatch": 20}, "--minibatch must be <= --train-batch"),
        ({"checkpoint_every": -1}, "--checkpoint-every must be an int >= 0, got -1"),
        ({"resume": True, "out": Path("/nonexistent/run")}, "--resume: no checkpoint in"),
    ],
)
def test_bad_options_name_the_argument(changes, message):
    with pytest.raises(ValueError, match=message):
        RLlibOptions(**changes)


def test_a_new_run_refuses_a_folder_that_holds_one(tmp_path):
    (tmp_path / "checkpoint").mkdir()
    with pytest.raises(ValueError, match="holds a run already: continue it with --resume"):
        RLlibOptions(out=tmp_path)
    assert RLlibOptions(out=tmp_path, resume=True).resume


def run(script: str, out: Path, *args: str) -> list[dict]:
    command = [sys.executable, str(ROOT / "examples" / script), *TINY, "--out", str(out), *args]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "iteration " in done.stdout
    assert (out / "checkpoint").is_dir()
    return json.loads((out / "progress.json").read_text())


@pytest.mark.extras
@needs_ray
def test_train_adversaries_rllib_with_an_env_runner(tmp_path):
    (row,) = run("train_adversaries_rllib.py", tmp_path, "--num-env-runners", "1")
    assert row["env_steps"] >= 40 and row["env_steps_per_s"] > 0


@pytest.mark.extras
@needs_ray
def test_train_ego_rllib_against_the_riskflow_adversary(tmp_path):
    (row,) = run("train_ego_rllib.py", tmp_path, "--max-agents", "6", "--k", "1")
    assert row["env_steps"] >= 40


@pytest.mark.extras
@needs_ray
def test_train_ego_rllib_checkpoints_and_resumes(tmp_path):
    """Two iterations with a checkpoint after each, then --resume up to three: the saved
    rows are kept and one more iteration runs from the restored algorithm."""
    first = run("train_ego_rllib.py", tmp_path, "--max-agents", "6", "--k", "1",
                "--iterations", "2", "--checkpoint-every", "1")  # fmt: skip
    assert [row["iteration"] for row in first] == [1, 2]
    resumed = run("train_ego_rllib.py", tmp_path, "--max-agents", "6", "--k", "1",
                  "--iterations", "3", "--resume")  # fmt: skip
    assert resumed[:2] == first and resumed[2]["iteration"] == 3
