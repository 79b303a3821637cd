"""riskflow-train's run folders: a loss that turns NaN stops the run, a folder that holds a
run is continued (only with the same training) or left alone, a resume logs each step once."""

from __future__ import annotations

import json

import pytest
import torch

from policies.learned.checkpoint import load_generator
from policies.train import GENERATOR, METRICS_LOG
from policies.train import main as train_main
from tests.policies.highway_banks import write_banks
from tests.policies.learned.test_trainer import tiny_args


@pytest.fixture(scope="module")
def banks(tmp_path_factory):
    """(train, val) scene folders: 3 and 1 highway scenes, as ``test_trainer``'s."""
    root = tmp_path_factory.mktemp("banks")
    return write_banks((root / "train", root / "val"), ([0, 2, 3], [4]))


def test_a_loss_that_turns_nan_stops_training_with_one_line(banks, tmp_path, tiny_config, capsys):
    """A learning rate far too large: the run stops at the first non-finite loss, before the
    step writes NaN into the weights, with one line and status 2 (it went on and saved NaN
    weights that every planner later refused)."""
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        train_main(tiny_args(banks, out, tiny_config, "--lr", "1e30", steps=6))
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "riskflow-train: error: the loss or its gradient is not finite at step" in error
    if (out / GENERATOR).is_file():  # a save before the divergence: finite weights
        model, _, _ = load_generator(out / GENERATOR)
        assert all(torch.isfinite(p).all() for p in model.parameters())


def test_a_run_folder_is_continued_or_left_alone(banks, tmp_path, tiny_config, refused):
    """A new training into a finished run's folder would overwrite it and mix two runs in
    its metrics log; a resume with other training options would silently be another run."""
    out = tmp_path / "run"
    train_main(tiny_args(banks, out, tiny_config, steps=2))
    with refused("holds a training run already .* continue it with --resume"):
        train_main(tiny_args(banks, out, tiny_config, steps=2))
    changed = ("--resume", "--lr", "0.5", "--batch-size", "3")  # the last --batch-size wins
    with refused(r"--batch-size 2 there, 3 now, --lr [0-9.e-]+ there, 0.5 now"):
        train_main(tiny_args(banks, out, tiny_config, *changed, steps=4))
    assert train_main(tiny_args(banks, out, tiny_config, "--resume", steps=3)) == 0  # longer


def test_a_resume_logs_each_step_once(banks, tmp_path, tiny_config):
    """Rows an interrupted run logged after its last checkpoint (and a torn one) are
    dropped: the resumed run logs those steps again."""
    out = tmp_path / "run"
    train_main(tiny_args(banks, out, tiny_config, steps=2))
    with (out / METRICS_LOG).open("a") as log:
        log.write(json.dumps({"step": 3, "train_loss": 1.0}) + "\n" + '{"step": 4, "tr')
    train_main(tiny_args(banks, out, tiny_config, "--resume", steps=4))
    steps = [json.loads(line)["step"] for line in (out / METRICS_LOG).read_text().splitlines()]
    assert steps == [1, 2, 3, 4]
