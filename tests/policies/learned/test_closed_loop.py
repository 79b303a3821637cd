"""Closed-loop training scenes (CAT-K style): the generator drives, the target returns."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from policies.closed_loop_data import MANIFEST, main
from policies.learned.adversary_config import default_window_config
from policies.learned.checkpoint import load_generator
from policies.learned.closed_loop import ClosedLoopConfig, closed_loop_scenes, return_actions
from policies.learned.data import WindowDataset
from policies.learned.windows import build_window, window_from_scenario
from riskflow_env import dynamics
from riskflow_env.scenarios import shipped_bank
from riskflow_env.scenarios.io import list_scenarios, save_scenario

SMALL = ClosedLoopConfig(cycles=4, every=2, iterations=60)


@pytest.fixture(scope="module")
def generator():
    model, normalizer, _ = load_generator()
    return model, normalizer, default_window_config(model.config)


@pytest.fixture(scope="module")
def scene():
    return shipped_bank("train")[2]  # a roundabout


@pytest.fixture(scope="module")
def made(generator, scene):
    model, normalizer, windows = generator
    return closed_loop_scenes(scene, model, normalizer, windows, SMALL, position=3)


def test_one_scene_per_cut_each_with_one_window(made, scene, generator):
    windows = generator[2]
    assert len(made) == 2  # cycles 2 and 4
    for out in made:
        assert out.states.shape[1] == windows.history_steps + windows.future_steps
        assert out.current_index == windows.history_steps - 1
        assert out.map is scene.map and out.source.endswith("closed-loop")
    data = WindowDataset(made, windows)
    assert len(data) == 2
    # the reached steps: 10 and 20 steps of closed loop after the scene's current step
    reached = [int(out.name.rsplit("-", 1)[1]) for out in made]
    assert reached == [scene.current_index + 10, scene.current_index + 20]


def test_history_is_the_log_before_the_drive_and_off_it_after(made, scene, generator):
    windows = generator[2]
    out, now = made[1], scene.current_index + 20
    start = now - windows.history_steps + 1
    logged = scene.states[:, start : now + 1]
    valid = scene.valid[:, start : now + 1]
    before = scene.current_index - start + 1  # the log's own steps
    np.testing.assert_array_equal(out.states[:, :before][valid[:, :before]],
                                  logged[:, :before][valid[:, :before]])  # fmt: skip
    history = out.states[:, before : windows.history_steps, :2]
    driven = np.linalg.norm(history - logged[:, before:, :2], axis=-1)
    assert driven[valid[:, before:]].max() > 0.05  # the generator drove, not the log


def test_the_window_actions_drive_its_future_and_return_to_the_log(made, scene, generator):
    windows = generator[2]
    out, now = made[1], scene.current_index + 20
    window = window_from_scenario(out, None, windows)
    rows, held = window.agent_index, window.future_valid
    driven = dynamics.rollout(window.history[:, -1].astype(np.float64),
                              window.actions.astype(np.float64), windows.dynamics)  # fmt: skip
    gap = np.linalg.norm(driven[..., :2] - window.future[..., :2], axis=-1)
    assert gap[held].max() < 1e-2  # the future is the rollout of the actions (float32 files)
    bounds = dynamics.clip_actions(window.actions, windows.dynamics)
    np.testing.assert_allclose(window.actions[window.actions_valid],
                               bounds[window.actions_valid], atol=1e-4)  # fmt: skip
    log = scene.states[rows, now + 1 : now + 1 + windows.future_steps, :2]
    world = out.states[rows, windows.history_steps :, :2]
    offset = np.linalg.norm(world - log, axis=-1)
    start = np.linalg.norm(out.states[rows, out.current_index, :2] - scene.states[rows, now, :2],
                           axis=-1)  # fmt: skip
    moved = held.all(axis=1) & (start > 0.3)
    assert moved.any()
    ratio = offset[moved, -1] / start[moved]  # < 1: nearer the log 5 s later than at the cut
    assert (ratio < 1).mean() > 0.75 and np.median(ratio) < 0.6  # most come back toward it


def test_agents_outside_the_window_keep_their_logged_future(generator, scene):
    model, normalizer, windows = generator
    few = dataclasses.replace(windows, max_agents=4)
    made = closed_loop_scenes(scene, model, normalizer, few, SMALL, position=0)
    out, now = made[0], scene.current_index + 10
    window = window_from_scenario(out, None, few)
    others = np.setdiff1d(np.arange(scene.num_agents), window.agent_index)
    future = slice(now + 1, now + few.future_steps + 1)
    valid = scene.valid[others, future]
    kept = out.states[others, few.history_steps :]
    np.testing.assert_array_equal(kept[valid], scene.states[others, future][valid])


def test_on_the_log_the_return_plan_is_the_log(scene, generator):
    windows = generator[2]
    window = window_from_scenario(scene, 60, windows)
    (plan,) = return_actions([window], windows.dynamics, SMALL)
    held = window.future_valid
    gap = np.linalg.norm(plan[..., :2] - window.future[..., :2], axis=-1)
    assert np.median(gap[held]) < 0.05


def test_an_agent_set_off_sideways_comes_back_smoothly(scene, generator):
    windows = generator[2]
    current = 60
    tracks = scene.states.copy()
    window = window_from_scenario(scene, current, windows)
    row = window.agent_index[1]
    heading = tracks[row, current, 3]
    shift = 1.5 * np.array([-np.sin(heading), np.cos(heading)])  # 1.5 m to the left
    tracks[row, current - 5 : current + 1, :2] += shift
    moved = build_window(tracks, scene.valid, scene.length, scene.width, scene.map,
                         window.agent_index, current, windows)  # fmt: skip
    config = dataclasses.replace(SMALL, iterations=200)
    (plan,) = return_actions([moved], windows.dynamics, config)
    gap = np.linalg.norm(plan[1, :, :2] - moved.future[1, :, :2], axis=-1)
    assert gap[0] > 1.2 and gap[30] < 0.5 and gap[-1] < 0.3
    actions = dynamics.inverse(np.concatenate([moved.history[1, -1:], plan[1]]), windows.dynamics)
    # no yaw jolt while it returns (the log itself may turn sharply later)
    assert np.abs(np.diff(actions[:30, 1])).max() / windows.dynamics.dt < 2.0


def test_same_seed_same_scenes_other_seed_others(generator, scene, made):
    model, normalizer, windows = generator
    again = closed_loop_scenes(scene, model, normalizer, windows, SMALL, position=3)
    for a, b in zip(made, again, strict=True):
        np.testing.assert_array_equal(a.states, b.states)
    other = closed_loop_scenes(scene, model, normalizer, windows,
                               dataclasses.replace(SMALL, seed=1), position=3)  # fmt: skip
    assert not np.array_equal(other[0].states, made[0].states)


def test_supervised_steps_keep_only_the_first_steps_of_the_return(generator, scene, made):
    model, normalizer, windows = generator
    config = dataclasses.replace(SMALL, supervised_steps=10)
    short = closed_loop_scenes(scene, model, normalizer, windows, config, position=3)
    kept = windows.history_steps + 10
    for full, cut in zip(made, short, strict=True):
        window = window_from_scenario(cut, None, windows)
        rows = window.agent_index
        assert not window.future_valid[:, 10:].any()
        first = np.arange(windows.future_steps) < 10
        logged = full.valid[rows, windows.history_steps :]
        np.testing.assert_array_equal(window.future_valid, logged & first)
        valid = cut.valid[:, :kept]
        np.testing.assert_array_equal(cut.states[:, :kept][valid], full.states[:, :kept][valid])


@pytest.mark.parametrize(
    ("field", "value"),
    [("candidates", 0), ("cycles", 1.5), ("along_weight", -1.0), ("learning_rate", 0.0),
     ("seed", "a"), ("supervised_steps", -1)],
)  # fmt: skip
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"ClosedLoopConfig.{field}"):
        ClosedLoopConfig(**{field: value})


def test_command_writes_a_folder_that_training_reads(tmp_path, capsys):
    bank = shipped_bank("train")
    source = tmp_path / "recorded"
    for i in (0, 2):
        save_scenario(bank[i], source / f"{i:05d}.npz", map_dir=source / "maps")
    out = tmp_path / "closed"
    argv = ["--data", str(source), "--out", str(out), "--cycles", "2", "--every", "1",
            "--iterations", "20"]  # fmt: skip
    assert main(argv) == 0
    assert "wrote 4 closed-loop scenes of 2 recorded" in capsys.readouterr().out
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["scenes"] == 4 and manifest["settings"]["cycles"] == 2
    assert len(list_scenarios(out)) == 4
    assert len(WindowDataset(out, default_window_config(load_generator()[0].config))) == 4
    assert main(argv) == 2  # --out now holds scenes
    assert "--out" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("extra", "named"),
    [(["--candidates", "0"], "--candidates"), (["--scenes", "-1"], "--scenes")],
)
def test_bad_options_are_usage_errors(tmp_path, extra, named, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--data", str(tmp_path), "--out", str(tmp_path / "o"), *extra])
    assert stop.value.code == 2 and named in capsys.readouterr().err


def test_missing_folder_and_cuda_without_cuda_name_the_option(tmp_path, capsys):
    assert main(["--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "--data" in capsys.readouterr().err
    if not torch.cuda.is_available():
        bank = shipped_bank("train")
        save_scenario(bank[0], tmp_path / "r" / "a.npz")
        argv = ["--data", str(tmp_path / "r"), "--out", str(tmp_path / "o"), "--device", "cuda"]
        assert main(argv) == 2
        assert "--device" in capsys.readouterr().err
