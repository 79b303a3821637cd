"""riskflow-train on several processes (torch.distributed, started by torchrun): the weights
of one process with the same global batch, only rank 0 writes, resume across layouts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from policies.learned.checkpoint import load_checkpoint
from policies.learned.distributed import Ranks, masked_mean, process_device
from policies.train import CHECKPOINT, METRICS_LOG
from policies.train import main as train_main
from tests.policies.highway_banks import write_banks

ROOT = Path(__file__).resolve().parents[3]


def _args(banks: tuple[Path, ...], out: Path, config, *extra: str) -> list[str]:
    """Tiny model; global batches of 3 windows (2 + 1 on two processes: shards of unequal
    size and agent counts); every loss term on, so each of its means is a global one."""
    return [
        "--data", str(banks[0]), "--val-data", str(banks[1]), "--out", str(out),
        "--model", json.dumps(config.to_dict()), "--stride", "16", "--batch-size", "3",
        "--steps", "4", "--eval-every", "2", "--log-every", "1", "--val-windows", "2",
        "--num-samples", "2", "--lr", "1e-3", "--collision-weight", "10",
        "--offroad-weight", "10", "--jerk-weight", "1", "--one-step-fraction", "0.25",
        "--recovery-copies", "1", "--recovery-parked", "1", *extra,
    ]  # fmt: skip


def _assert_same_weights(a: dict, b: dict, atol: float) -> None:
    for key, value in a["state_dict"].items():
        torch.testing.assert_close(b["state_dict"][key], value, rtol=0, atol=atol)
        raw = a["training"]["raw_state_dict"][key], b["training"]["raw_state_dict"][key]
        torch.testing.assert_close(raw[1], raw[0], rtol=0, atol=atol)


def test_torchrun_subprocesses_train_the_weights_of_one_process_and_resume_on_one(
    tmp_path, tiny_config
):
    """torchrun, 2 CPU processes (gloo), 2 of 4 steps: the weights of one process to 1e-5;
    only rank 0 logs; then one process resumes to step 4 and ends where an uninterrupted
    one-process run ends."""
    banks = write_banks((tmp_path / "train", tmp_path / "val"), ([0, 2, 3], [4]))
    two, one, straight = tmp_path / "two", tmp_path / "one", tmp_path / "straight"
    assert train_main(_args(banks, one, tiny_config, "--stop-step", "2")) == 0  # caches too
    launch = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command = [*launch, "--nproc_per_node", "2", "-m", "policies.train"]
    done = subprocess.run(
        [*command, *_args(banks, two, tiny_config, "--stop-step", "2")],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    parallel, single = load_checkpoint(two / CHECKPOINT), load_checkpoint(one / CHECKPOINT)
    assert parallel["step"] == 2 and parallel["train_config"]["processes"] == 2
    _assert_same_weights(single, parallel, atol=1e-5)
    assert parallel["metrics"]["train_loss"] == pytest.approx(single["metrics"]["train_loss"])
    logged = [json.loads(line)["step"] for line in (two / METRICS_LOG).read_text().splitlines()]
    assert logged == [1, 2]  # one writer
    assert train_main(_args(banks, straight, tiny_config)) == 0
    assert train_main(_args(banks, two, tiny_config, "--resume")) == 0
    _assert_same_weights(
        load_checkpoint(straight / CHECKPOINT), load_checkpoint(two / CHECKPOINT), 1e-5
    )


def test_shards_split_a_global_batch_and_one_process_is_unchanged():
    shards = [Ranks(rank, 3).shard(8) for rank in range(3)]
    assert [(s.start, s.stop, s.total) for s in shards] == [(0, 3, 8), (3, 6, 8), (6, 8, 8)]
    whole = Ranks().shard(5)
    draws = torch.arange(5.0)
    assert whole.rows(draws).data_ptr() == draws.data_ptr() and len(whole.rows(draws)) == 5
    total, count = torch.tensor(6.0), torch.tensor(4)
    assert masked_mean(total, count) == 1.5 and masked_mean(total, count * 0) == 6.0
    assert process_device("cuda", Ranks(1, 2, local=1)) == "cuda:1"
    assert (
        process_device("cpu", Ranks(1, 2)) == "cpu"
        and process_device("cuda:1", Ranks()) == "cuda:1"
    )
    with pytest.raises(ValueError, match="--device: give 'cuda'"):
        process_device("cuda:1", Ranks(0, 2))
