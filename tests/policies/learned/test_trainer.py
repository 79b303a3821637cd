"""riskflow-train: end-to-end runs on a tiny scene bank, resume, options, batch order."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from policies.dataclass_cli import parse_dataclass
from policies.learned.batches import batch_order, load_splits
from policies.learned.checkpoint import load_checkpoint, load_generator
from policies.learned.config import ModelConfig
from policies.learned.generator import CheckpointError
from policies.learned.recovery import RecoveryConfig
from policies.learned.train_options import learning_rate
from policies.riskflow.time_sampler import TimeSampler
from policies.train import CHECKPOINT, GENERATOR, METRICS_LOG, TrainOptions, objective
from policies.train import main as train_main
from tests.policies.highway_banks import write_banks

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def banks(tmp_path_factory) -> tuple[Path, Path]:
    """(train, val) scene folders as written by ``riskflow-data``: 3 and 1 highway scenes."""
    root = tmp_path_factory.mktemp("banks")
    return write_banks((root / "train", root / "val"), ([0, 2, 3], [4]))


def tiny_args(
    banks: tuple[Path, Path], out: Path, config: ModelConfig, *extra: str, steps: int = 4
) -> list[str]:
    """A fast command line: tiny model, stride 16, batches of 2 windows."""
    return [
        "--data", str(banks[0]), "--val-data", str(banks[1]), "--out", str(out),
        "--model", json.dumps(config.to_dict()), "--stride", "16", "--batch-size", "2",
        "--steps", str(steps), "--eval-every", "2", "--log-every", "1",
        "--val-windows", "3", "--num-samples", "2", *extra,
    ]  # fmt: skip


def test_main_trains_end_to_end(banks, tmp_path, tiny_config):
    out = tmp_path / "run"
    assert train_main(tiny_args(banks, out, tiny_config)) == 0
    lines = [json.loads(line) for line in (out / METRICS_LOG).read_text().splitlines()]
    assert [line["step"] for line in lines] == [1, 2, 3, 4]
    final = lines[-1]
    for key in ("val_ade", "val_fde", "val_min_ade", "val_cv_ade", "val_cv_fde", "val_jerk_rms"):
        assert np.isfinite(final[key]), key
    assert final["val_min_ade"] <= final["val_ade"] + 5.0
    assert final["train_samples_per_s"] > 0 and np.isfinite(final["train_loss"])
    assert final["train_dudt_abs"] >= 0  # the MeanFlow objective ran
    full = load_checkpoint(out / CHECKPOINT)
    assert full["step"] == 4 and "training" in full
    assert full["train_config"]["stride"] == 16 and full["metrics"]["val_ade"] == final["val_ade"]
    assert set(full["version"]) == {"riskflow_env", "git_commit", "git_dirty"}
    assert (banks[0] / "norm_stats.json").is_file()
    model, normalizer, metadata = load_generator(out / GENERATOR)
    assert model.config == tiny_config and not model.training
    assert normalizer.to_dict() == full["normalizer"]
    assert metadata["step"] == 4 and "training" not in load_checkpoint(out / GENERATOR)


COSINE = ("--lr-schedule", "cosine", "--warmup-steps", "1")


@pytest.mark.parametrize(
    ("schedule", "stop", "stopped_at"),
    [
        ((), ("--steps", "2"), 2),
        (COSINE, ("--time-budget-min", "1e-9"), 1),
        (COSINE, ("--stop-step", "3"), 3),
    ],
    ids=["constant", "cosine-budget", "cosine-stop-step"],
)
def test_resume_gives_the_uninterrupted_result(
    banks, tmp_path, tiny_config, schedule, stop, stopped_at
):
    """A run stopped early, then --resume up to 4: bit-identical to 4 steps in one go
    (CPU), with the learning-rate schedule too (a function of the step and --steps: the
    cosine runs are stopped by a time budget after one of their 4 steps, or by
    --stop-step, which repeats such a run's steps on any machine)."""
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    train_main(tiny_args(banks, straight, tiny_config, *schedule))
    train_main(tiny_args(banks, resumed, tiny_config, *schedule, *stop))
    early = load_checkpoint(resumed / CHECKPOINT)
    assert early["step"] == stopped_at
    rates = [
        [json.loads(line)["train_lr"] for line in (run / METRICS_LOG).read_text().splitlines()]
        for run in (straight, resumed)
    ]
    assert rates[1] == rates[0][:stopped_at]  # the uninterrupted run's schedule
    train_main(tiny_args(banks, resumed, tiny_config, *schedule, "--resume"))
    a, b = load_checkpoint(straight / CHECKPOINT), load_checkpoint(resumed / CHECKPOINT)
    assert b["step"] == 4
    for key in a["state_dict"]:
        torch.testing.assert_close(a["state_dict"][key], b["state_dict"][key], rtol=0, atol=0)
        raw_a, raw_b = a["training"]["raw_state_dict"], b["training"]["raw_state_dict"]
        torch.testing.assert_close(raw_a[key], raw_b[key], rtol=0, atol=0)
    assert a["metrics"]["val_ade"] == b["metrics"]["val_ade"]
    torch.testing.assert_close(a["training"]["rng"]["noise"], b["training"]["rng"]["noise"])


def test_resume_with_another_architecture_names_the_mismatch(
    banks, tmp_path, tiny_config, capsys, refused
):
    out = tmp_path / "run"
    train_main(tiny_args(banks, out, tiny_config, steps=1))
    wider = dataclasses.replace(tiny_config, head_dim=64)
    with pytest.raises(SystemExit) as exit_info:  # one line, no traceback
        train_main(tiny_args(banks, out, wider, "--resume"))
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert "riskflow-train: error: " in error and "head_dim" in error
    with pytest.raises(CheckpointError, match="head_dim"):
        train_main(tiny_args(banks, out, wider, "--resume", "--debug"))
    with refused("--resume: no checkpoint"):
        train_main(tiny_args(banks, tmp_path / "empty", tiny_config, "--resume"))


def test_init_fine_tunes_from_a_checkpoint_and_resumes(
    banks, tmp_path, tiny_config, refused, capsys
):
    """--init starts from the weights and statistics of a generator file; a fine-tune
    with recovery windows resumes like any run; a wrong --init names the problem."""
    base = tmp_path / "base"
    train_main(tiny_args(banks, base, tiny_config, steps=2))
    start = load_checkpoint(base / GENERATOR)
    tune = tmp_path / "tune"
    args = ["--init", str(base / GENERATOR), "--recovery-copies", "1", "--lr", "1e-9"]
    train_main(tiny_args(banks, tune, tiny_config, *args, steps=1))
    tuned = load_checkpoint(tune / CHECKPOINT)
    assert tuned["normalizer"] == start["normalizer"] and tuned["step"] == 1
    assert tuned["train_config"]["init"] == str(base / GENERATOR)
    for key, value in start["state_dict"].items():  # lr 1e-9: still the initial weights
        torch.testing.assert_close(tuned["state_dict"][key], value, rtol=0, atol=1e-6)
    cached = {p.name for p in (banks[0] / "cache").iterdir()}
    assert any(name.startswith("windows-stride16-recovery-") for name in cached)
    capsys.readouterr()
    train_main(tiny_args(banks, tune, tiny_config, *args, "--resume", steps=2))
    assert load_checkpoint(tune / CHECKPOINT)["step"] == 2
    assert f"riskflow-train: wrote {tune / GENERATOR} (to plan with)" in capsys.readouterr().err
    train_main(tiny_args(banks, tune, tiny_config, *args, "--resume", steps=2))
    error = capsys.readouterr().err
    assert "is at step 2, --steps is 2: nothing left to train" in error and "wrote" not in error
    with refused("--init: no generator checkpoint"):
        train_main(tiny_args(banks, tmp_path / "x", tiny_config, "--init", str(tmp_path / "no.pt")))
    wider = dataclasses.replace(tiny_config, head_dim=64)
    with refused("--init: .*head_dim"):
        train_main(tiny_args(banks, tmp_path / "y", wider, "--init", str(base / GENERATOR)))
    diffusion = ("--init", str(base / GENERATOR), "--generator", "diffusion")
    with refused("--init: .* meanflow generator, not diffusion"):
        train_main(tiny_args(banks, tmp_path / "z", tiny_config, *diffusion))


def test_flow_matching_reference_and_time_budget(banks, tmp_path, tiny_config):
    out = tmp_path / "fm"
    train_main(tiny_args(banks, out, tiny_config, "--flow-matching", "--time-budget-min", "1e-9"))
    state = load_checkpoint(out / GENERATOR)
    assert state["step"] == 1, "the time budget stops after the first step"
    assert state["train_config"]["flow_matching"] is True
    assert "train_dudt_abs" not in state["metrics"] and np.isfinite(state["metrics"]["val_ade"])


def test_val_fraction_splits_scenes(banks, tmp_path, tiny_config):
    args = tiny_args(banks, tmp_path / "split", tiny_config, "--val-fraction", "0.34", steps=1)
    del args[args.index("--val-data") : args.index("--val-data") + 2]
    train_main(args)
    metrics = load_checkpoint(tmp_path / "split" / GENERATOR)["metrics"]
    assert metrics["val_windows"] == 3  # one held-out scene, --val-windows 3
    cached = {p.name for p in (banks[0] / "cache").iterdir()}
    assert {"windows-stride16-val0.34-train.npz", "windows-stride16-val0.34-val.npz"} <= cached


def test_several_data_folders_train_on_their_scenes_together(banks, tmp_path, tiny_config):
    """``--data A B``: the windows of A's scenes then B's, as from one folder holding both
    (recovery draws included: scene positions run on across the folders)."""
    parts = write_banks((tmp_path / "a", tmp_path / "b"), ([0, 2], [3]))
    recovery = RecoveryConfig(copies=1, parked=1, seed=0)
    together, _ = load_splits(list(parts), banks[1], 0.1, 16, recovery)
    one, _ = load_splits(banks[0], banks[1], 0.1, 16, recovery)
    np.testing.assert_array_equal(together.index, one.index)
    for item in range(len(one)):
        for field in dataclasses.fields(one[item]):
            expected = getattr(one[item], field.name)
            got = getattr(together[item], field.name)
            np.testing.assert_array_equal(got, expected, err_msg=field.name)
    assert [p.name for p in (parts[0] / "cache").iterdir()] == [
        p.name for p in (parts[0] / "cache").glob("windows-stride16-recovery-*-with-*.npz")
    ]
    out = tmp_path / "run"
    args = tiny_args(banks, out, tiny_config, steps=1)
    args[args.index("--data") + 1 : args.index("--data") + 2] = map(str, parts)
    assert train_main(args) == 0
    assert load_checkpoint(out / GENERATOR)["train_config"]["data"] == list(map(str, parts))
    assert not (parts[0] / "norm_stats.json").exists()  # computed over both, not cached


def test_several_data_folders_need_a_validation_folder(banks, tmp_path, tiny_config, capsys):
    args = tiny_args(banks, tmp_path / "run", tiny_config, steps=1)
    args[args.index("--data") + 1 : args.index("--val-data") + 2] = [str(banks[0])] * 2
    with pytest.raises(SystemExit):
        train_main(args)
    assert "--val-data with several --data folders (got 2" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--val-data"):
        load_splits([banks[0], banks[0]], None, 0.1, 16)


def test_cli_subprocess_smoke(banks, tmp_path, tiny_config):
    out = tmp_path / "cli"
    args = tiny_args(banks, out, tiny_config, steps=1)
    done = subprocess.run(
        [sys.executable, "-m", "policies.train", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "samples_s" in done.stderr and "DeprecationWarning" not in done.stderr
    assert (out / GENERATOR).is_file()


def test_options_are_typed_documented_and_checked(capsys):
    options = parse_dataclass(TrainOptions, ["--data", "d", "--steps", "7", "--flow-matching"])
    assert options == TrainOptions(data=Path("d"), steps=7, flow_matching=True)
    assert options.val_data is None and options.lr == 1e-4 and options.ema_decay == 0.995
    with pytest.raises(SystemExit):
        parse_dataclass(TrainOptions, ["--data", "d", "--steps", "0"], "riskflow-train")
    assert "--steps" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_dataclass(TrainOptions, ["--help"], "riskflow-train")
    assert "EMA decay of the weights per step" in capsys.readouterr().out


def test_learning_rate_schedules():
    """Constant by default; cosine warms up linearly, peaks at --lr, halves midway, decays
    towards 0 at --steps; the logged rate is the one used; bad values (--stop-step past
    --steps too) name the option."""
    constant = TrainOptions(data=Path("d"), steps=100, lr=1e-3)
    assert [learning_rate(constant, step) for step in (0, 50, 99)] == [1e-3] * 3
    cosine = dataclasses.replace(constant, lr_schedule="cosine", warmup_steps=10)
    rates = np.array([learning_rate(cosine, step) for step in range(100)])
    np.testing.assert_allclose(rates[:3], 1e-3 * np.array([0.1, 0.2, 0.3]), rtol=1e-2)
    assert rates.argmax() == 9 and rates[9] <= 1e-3
    assert learning_rate(cosine, 50) == pytest.approx(0.5e-3)
    assert np.all(np.diff(rates[9:]) < 0) and 0 < rates[-1] < 1e-6
    no_warmup = dataclasses.replace(cosine, warmup_steps=0)
    assert learning_rate(no_warmup, 0) == 1e-3
    with pytest.raises(ValueError, match="--lr-schedule in"):
        dataclasses.replace(constant, lr_schedule="linear")
    with pytest.raises(ValueError, match="--warmup-steps < --steps"):
        dataclasses.replace(cosine, warmup_steps=100)
    for stop in (-1, 101):
        with pytest.raises(ValueError, match="--stop-step <= --steps"):
            dataclasses.replace(cosine, stop_step=stop)


def test_logged_learning_rate_follows_the_schedule(banks, tmp_path, tiny_config):
    out = tmp_path / "cosine"
    train_main(tiny_args(banks, out, tiny_config, "--lr", "1e-3", "--lr-schedule", "cosine"))
    logged = [json.loads(line)["train_lr"] for line in (out / METRICS_LOG).read_text().splitlines()]
    options = TrainOptions(data=Path("d"), steps=4, lr=1e-3, lr_schedule="cosine")
    assert logged == pytest.approx([learning_rate(options, step) for step in range(4)])


def test_realism_penalties_reach_the_loss_and_bad_weights_name_the_option(
    banks, tmp_path, tiny_config
):
    out = tmp_path / "penalties"
    weights = ["--collision-weight", "10", "--offroad-weight", "10", "--jerk-weight", "0.03"]
    assert train_main(tiny_args(banks, out, tiny_config, *weights, steps=2)) == 0
    logged = [json.loads(line) for line in (out / METRICS_LOG).read_text().splitlines()]
    for line in logged:  # each penalty is computed and logged once its weight is set
        assert all(np.isfinite(line[f"train_{name}"]) for name in ("overlap", "offroad", "jerk"))
        assert line["train_jerk"] > 0  # an untrained plan is rough
    assert load_checkpoint(out / GENERATOR)["train_config"]["jerk_weight"] == 0.03
    with pytest.raises(ValueError, match="--jerk-weight finite and >= 0"):
        TrainOptions(data=Path("d"), jerk_weight=-1.0)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"steps": 0}, r"--steps must be an int in \[1, 100000000\], got 0"),
        ({"steps": 10**12}, r"--steps must be an int in \[1, 100000000\]"),
        ({"log_every": -1}, "--log-every must be an int >= 1, got -1"),
        ({"lr": math.inf}, "--lr finite and > 0"),
        ({"lr": math.nan}, "--lr finite and > 0"),
        ({"time_budget_min": math.nan}, "--time-budget-min finite and >= 0"),
        ({"device": "gpu"}, "--device: 'gpu' is not a torch device"),
        ({"out": "FILE"}, "--out: .*FILE exists and is not a folder"),
        ({"threads": -1}, r"--threads must be an int in \[0, 256\], got -1"),
        ({"threads": 1000}, r"--threads must be an int in \[0, 256\], got 1000"),
        ({"seed": -1}, r"--seed must be an int in \[0, 4294967295\], got -1"),
        ({"val_windows": -1}, "--val-windows must be an int >= 0, got -1"),
        ({"heading_weight": -1.0}, "--action-weight, --heading-weight, .* finite and >= 0"),
        ({"action_weight": math.nan}, "--action-weight, --heading-weight, .* finite and >= 0"),
        ({"lr": True}, "--lr must be a number, got True"),
        ({"steps": "5"}, "--steps must be an int, got '5'"),
        ({"model": "{bad"}, "--model: Expecting property name"),
        ({"model": "[1]"}, "--model: expected a JSON object of ModelConfig fields"),
        ({"model": '{"head_dim": "x"}'}, "--model: ModelConfig.head_dim must be"),
        ({"model": "nowhere.json"}, "--model: .*No such file"),
    ],
)
def test_bad_options_name_the_flag_before_any_data_is_read(changes, message, tmp_path):
    (tmp_path / "FILE").write_text("")
    changes = {k: tmp_path / v if v == "FILE" else v for k, v in changes.items()}
    with pytest.raises(ValueError, match=message):
        TrainOptions(data=Path("d"), **changes)


def test_one_step_share_trains_at_the_samplers_call_and_bad_shares_name_the_option(
    banks, tmp_path, tiny_config
):
    out = tmp_path / "one_step"
    args = tiny_args(banks, out, tiny_config, "--one-step-fraction", "1", "--jerk-weight", "1")
    assert train_main(args) == 0  # every pair at (t, r) = (0, 1): finite, the JVP included
    logged = [json.loads(line) for line in (out / METRICS_LOG).read_text().splitlines()]
    assert all(np.isfinite(line["train_loss"]) and line["train_jerk"] > 0 for line in logged)
    assert load_checkpoint(out / GENERATOR)["train_config"]["one_step_fraction"] == 1.0
    assert objective(TrainOptions(data=Path("d"), one_step_fraction=0.1)).times == TimeSampler(
        one_step_fraction=0.1
    )
    for bad in ({"one_step_fraction": 1.5}, {"equal_fraction": math.nan}):
        with pytest.raises(ValueError, match="--equal-fraction, --one-step-fraction in"):
            TrainOptions(data=Path("d"), **bad)
    with pytest.raises(ValueError, match="--one-step-fraction only with --generator meanflow"):
        TrainOptions(data=Path("d"), one_step_fraction=0.1, flow_matching=True)


def test_batch_order_is_seeded_and_buckets_agent_counts():
    agents = np.random.default_rng(0).integers(1, 33, size=103)
    order = batch_order(agents, 4, 8, seed=1, epoch=2)
    np.testing.assert_array_equal(order, batch_order(agents, 4, 8, seed=1, epoch=2))
    assert order.shape == (25, 4) and len(np.unique(order)) == 100
    assert not np.array_equal(order, batch_order(agents, 4, 8, seed=1, epoch=3))
    spread = np.ptp(agents[order], axis=1).mean()
    plain = np.ptp(agents[batch_order(agents, 4, 1, seed=1, epoch=2)], axis=1).mean()
    assert spread < 0.5 * plain, (spread, plain)


def test_bad_data_folders_name_the_argument(banks, tmp_path, tiny_config, refused):
    pickled = tmp_path / "scene.pkl"
    pickled.write_bytes(b"")
    args = tiny_args(banks, tmp_path / "run", tiny_config)
    args[args.index("--data") + 1] = str(pickled)
    with refused(r"--data: .*is a file.*load_scenarionet"):
        train_main(args)
    args = tiny_args(banks, tmp_path / "run", tiny_config)
    args[args.index("--val-data") + 1] = str(tmp_path / "missing")
    with refused(r"--val-data: .*does not exist"):
        train_main(args)


def test_training_on_the_shipped_bank_writes_nothing_into_the_package(
    monkeypatch, tmp_path, tiny_config
):
    """Window caches and norm_stats.json of the installed bank go to the user cache."""
    from policies.learned.data_cache import CACHE_ENV
    from riskflow_env.scenarios.io import ASSETS

    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    before = sorted(ASSETS.rglob("*"))
    args = tiny_args((ASSETS / "train", None), tmp_path / "run", tiny_config, steps=1)
    del args[args.index("--val-data") : args.index("--val-data") + 2]
    assert train_main([*args, "--stride", "80"]) == 0
    assert sorted(ASSETS.rglob("*")) == before
    assert list((tmp_path / "user-cache").rglob("norm_stats.json"))
