"""The example scripts, run as a user would (subprocess) with tiny settings."""

from __future__ import annotations

import json
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from policies.learned.checkpoint import DEFAULT_NAME, build_checkpoint, save_checkpoint
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from riskflow_env.scenarios import load_scenario
from riskflow_env.wrappers import read_event_log
from tests.scripts import load_script

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
SHIPPED = ROOT / "policies" / "checkpoints" / DEFAULT_NAME
TINY = ModelConfig(
    encoder_dim=16,
    head_dim=32,
    context_dim=32,
    edge_dim=8,
    num_heads=2,
    encoder_layers=1,
    head_layers=1,
    map_widths=(4, 8),
    time_frequencies=8,
)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """An untrained tiny generator: the scripts' plumbing, not the model, is under test."""
    torch.manual_seed(0)
    model = RiskFlowGenerator(TINY)
    normalizer = ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.05))
    content = build_checkpoint(model, normalizer, step=0, train_config={}, metrics={})
    return save_checkpoint(content, tmp_path_factory.mktemp("model") / "tiny.pt")


def run(script: str, *args: str | Path) -> str:
    """Run an example; its stdout (fails the test with stderr on a non-zero exit)."""
    command = [sys.executable, str(EXAMPLES / script), *map(str, args)]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_rollout(checkpoint, tmp_path):
    out = run("rollout.py", "--steps", "10", "--checkpoint", checkpoint, "--out", tmp_path,
              "--k", "2", "--seed", "1")  # fmt: skip
    events = read_event_log(tmp_path / "events.jsonl")
    assert events[-1]["event"] == "episode_summary"
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert 1 <= metrics["steps"] <= 10 and metrics["planning_cycles"] >= 1
    assert "metrics:" in out and "planning_time_ms" in out
    import imageio.v3 as iio

    frames = iio.imread(tmp_path / "rollout.gif", index=None)
    assert frames.shape == (metrics["steps"] + 1, 360, 640, 3)


def test_rollout_warm_up_leaves_the_episode_as_it_is(checkpoint, tmp_path, monkeypatch):
    """The untimed warm-up step runs a throwaway adversary: the episode's events and
    metrics (all but the wall times) are those of a run without it."""
    rollout = load_script("examples/rollout.py")
    runs = {}
    for warm in (True, False):
        if not warm:
            monkeypatch.setattr(rollout, "warm_up", lambda *args: None)
        out = tmp_path / str(warm)
        options = rollout.Options(
            steps=12, checkpoint=checkpoint, out=out, k="2", seed=1, video="none"
        )
        metrics = rollout.main(options)
        timing = {"planning_time_ms", "planning_time_max_ms", "ego_time_ms"}
        events = [
            {key: value for key, value in event.items() if "time_" not in key}
            for event in read_event_log(out / "events.jsonl")
        ]
        runs[warm] = ({k: v for k, v in metrics.items() if k not in timing}, events)
    assert runs[True] == runs[False]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--video", "avi"], "--video must be one of"),
        (["--avoid-steps", "-1"], "--avoid-steps must be >= 0"),
        (["--hold-distance", "-2"], "--hold-distance must be finite and >= 0, got -2"),
        (["--lambda-map", "-1"], "--lambda-map must be finite and >= 0"),
        (["--planning-interval", "0.25"], "--planning-interval: 0.25 s is not a positive multiple"),
        (["--planning-interval", "nan"], "--planning-interval: nan s is not a positive multiple"),
        (["--planning-interval", "0"], "--planning-interval: 0.0 s is not a positive multiple"),
        (["--planning-interval", "6"], "--planning-interval: 6.0 s exceeds the plan horizon"),
        (["--planning-interval", "-0.5"], "--planning-interval: -0.5 s is not a positive"),
        (["--planning-interval", "inf"], "--planning-interval: inf s is not a positive"),
        (["--seed", "-1"], "--seed must be an int >= 0, got -1"),
        (["--device", "cdua"], "--device: 'cdua' is not a torch device"),
        (["--replay-mode", "open-loop"], "--replay-mode must be one of ('tracking', 'open_loop')"),
        (["--scenario", ""], "--scenario is empty: give a shipped bank index or a scenario file"),
        (["--checkpoint", str(EXAMPLES), "--steps", "1"], "--checkpoint: "),  # a folder
    ],
)
def test_rollout_rejects_bad_options(argv, message, monkeypatch, capsys):
    """The script's ``__main__`` block, run in this process (``runpy``, as ``python
    examples/rollout.py ...`` runs it, without starting an interpreter per option)."""
    script = EXAMPLES / "rollout.py"
    monkeypatch.setattr(sys, "argv", [str(script), *argv])
    monkeypatch.syspath_prepend(str(EXAMPLES))  # as when run: its folder first
    with pytest.raises(SystemExit) as exit_:
        runpy.run_path(str(script), run_name="__main__")
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def test_rollout_replay_tracks_the_log_unless_told_otherwise():
    """Replay steers onto the logged positions by default (inverse dynamics alone drift a
    recorded log's vehicles off the road); ``--replay-mode open_loop`` is ReplayPolicy's
    exact replay of a future these dynamics produced."""
    rollout = load_script("examples/rollout.py")
    assert rollout.make_traffic(rollout.Options(traffic="replay")).mode == "tracking"
    exact = rollout.Options(traffic="replay", replay_mode="open_loop")
    assert rollout.make_traffic(exact).mode == "open_loop"


@pytest.mark.skipif(not SHIPPED.is_file(), reason="the shipped checkpoint is not trained yet")
def test_rollout_with_the_shipped_checkpoint(tmp_path):
    run("rollout.py", "--steps", "5", "--video", "none", "--out", tmp_path)
    assert read_event_log(tmp_path / "events.jsonl")[-1]["event"] == "episode_summary"


def test_stress_test_writes_the_report_and_replay_files(checkpoint, tmp_path):
    out = run("stress_test_planner.py", "--scenes", "2", "--steps", "10", "--gifs", "1",
              "--no-progress", "--checkpoint", checkpoint, "--out", tmp_path)  # fmt: skip
    assert "avoidable failures" in out
    result = json.loads((tmp_path / "summary.json").read_text())
    assert result["ego_collision_rate"]["n"] == 2 and len(result["per_episode"]) == 2
    assert result["planner"] == "examples/stress_test_planner.py:my_planner"
    assert (tmp_path / "report.html").is_file() and (tmp_path / "report.md").is_file()
    for row in result["per_episode"]:
        if row["replay"]:  # a replay file is a scenario file: the documented command runs
            assert load_scenario(tmp_path / row["replay"]).name == row["scene"]
            out = run("rollout.py", "--scenario", tmp_path / row["replay"], "--traffic",
                      "replay", "--video", "none", "--out", tmp_path / "replay")  # fmt: skip
            assert "closed-loop" in out


def test_my_planner_returns_bounded_actions():
    module = load_script("examples/stress_test_planner.py")
    rng = np.random.default_rng(0)
    for _ in range(20):
        observation = rng.normal(0.0, 5.0, 142).astype(np.float32)
        observation[0] = abs(observation[0])
        accel, yaw_rate = module.my_planner(observation, None)
        assert -8.0 <= accel <= 5.0 and abs(yaw_rate) <= 1.0


def test_rollout_scenario_formats(monkeypatch, tmp_path):
    rollout = load_script("examples/rollout.py")
    pickled = tmp_path / "toy.pkl"
    pickled.write_bytes(b"")
    monkeypatch.setattr(rollout, "load_scenarionet", lambda path: ("scenarionet", path))
    assert rollout.load_scene(str(pickled)) == ("scenarionet", pickled)
    other = tmp_path / "scene.json"
    other.write_text("{}")
    with pytest.raises(ValueError, match=r"--scenario .*\.npz.*\.pkl"):
        rollout.load_scene(str(other))
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"--scenario .*broken\.npz"):
        rollout.load_scene(str(broken))
