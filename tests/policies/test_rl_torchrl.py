"""``examples/train_ego_torchrl.py`` (the ``torchrl`` extra): two tiny iterations, a
checkpoint that loads with ``weights_only=True``, a resume up to three, the sampled
maneuvers inside the action mask, and a clean stop on SIGTERM."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

pytestmark = pytest.mark.extras
pytest.importorskip(
    "torchrl", reason="torchrl is not installed (pip install -e '.[torchrl]'; .ci/run installs it)"
)
pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

ROOT = Path(__file__).resolve().parents[2]
TINY = ("--frames-per-batch", "64", "--minibatch", "32", "--epochs", "1", "--scenes", "2",
        "--episode-steps", "20", "--guidance-steps", "2", "--checkpoint-every", "1")  # fmt: skip


def command(out: Path, *args: str) -> list[str]:
    script = ROOT / "examples" / "train_ego_torchrl.py"
    return [sys.executable, str(script), *TINY, "--out", str(out), *args]


def test_trains_checkpoints_and_resumes(tmp_path):
    first = subprocess.run(command(tmp_path, "--iterations", "2"), capture_output=True,
                           text=True, cwd=ROOT, timeout=300)  # fmt: skip
    assert first.returncode == 0, first.stderr[-3000:]
    assert "iteration 2: 128 decisions" in first.stdout
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert int(state["iteration"]) == 2 and {"actor", "value", "vecnorm"} <= set(state)
    resumed = subprocess.run(command(tmp_path, "--iterations", "3", "--resume"),
                             capture_output=True, text=True, cwd=ROOT, timeout=300)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "resuming" in resumed.stdout and "iteration 3: 192 decisions" in resumed.stdout
    rows = json.loads((tmp_path / "progress.json").read_text())
    assert [row["iteration"] for row in rows] == [1, 2, 3]
    again = subprocess.run(command(tmp_path, "--iterations", "1"), capture_output=True,
                           text=True, cwd=ROOT, timeout=300)  # fmt: skip
    assert again.returncode == 2 and "holds a run already" in again.stderr


def test_sampled_maneuvers_respect_the_action_mask():
    from tests.scripts import load_script

    module = load_script("examples/train_ego_torchrl.py")
    options = module.Options(scenes=2, episode_steps=20, guidance_steps=2)
    env = module.make_env(options, seed=0)
    actor, _ = module.make_modules(env)
    rollout = env.rollout(40, actor, break_when_any_done=False)
    chosen = rollout["action"]
    mask = rollout["action_mask"]
    assert mask.dtype == torch.bool and mask.shape[-1] == 15
    assert mask.gather(-1, chosen.long().unsqueeze(-1)).all()


def test_sigterm_saves_and_exits_with_one_line(tmp_path):
    process = subprocess.Popen(
        command(tmp_path, "--iterations", "1000"), cwd=ROOT, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while not (tmp_path / "checkpoint.pt").is_file():
            assert process.poll() is None and time.monotonic() < deadline
            time.sleep(0.5)
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=240)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1].startswith("train_ego_torchrl.py: stopped by SIGTERM")
