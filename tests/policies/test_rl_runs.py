"""Training tools that behave (issue 55): Ctrl-C / SIGTERM save a checkpoint and exit with
one line, ``--resume`` goes on from it (bit for bit from the checkpoint), an interrupted run
evaluates, and every wrong path given to the scripts is one line naming the argument.

Needs the ``rl`` extra; tiny budgets, a 2-guidance-step adversary, no timing assertions
(the tests wait for files, not for durations).
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

from policies.rl.runs import RunError, find_model, make_run_folder, run_begun  # noqa: E402
from tests.scripts import load_script  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TINY = ("--n-steps", "32", "--batch-size", "64", "--n-epochs", "1", "--num-envs", "2",
        "--scenes", "3", "--episode-steps", "20", "--guidance-steps", "2",
        "--checkpoint-every", "64", "--seed", "3")  # fmt: skip


def script(name: str, *args: str | Path) -> list[str]:
    return [sys.executable, str(ROOT / "examples" / name), *map(str, args)]


def run(name: str, *args: str | Path) -> subprocess.CompletedProcess:
    done = subprocess.run(
        script(name, *args), capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def interrupt(out: Path, signum: int, vec_env: str) -> subprocess.CompletedProcess:
    """Start a long training, wait for its first checkpoint after the start, send ``signum``
    (SIGINT to the whole process group, as a terminal's Ctrl-C does; SIGTERM to the main
    process, as ``kill`` does) and return the finished process."""
    command = script("train_ego_ppo.py", *TINY, "--total-timesteps", "100000",
                     "--vec-env", vec_env, "--out", out)  # fmt: skip
    process = subprocess.Popen(
        command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while not (out / "checkpoints" / "ppo_64_steps.zip").is_file():
            assert process.poll() is None, process.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "no checkpoint within 240 s"
            time.sleep(0.5)
        if signum == signal.SIGINT:
            os.killpg(process.pid, signum)
        else:
            process.send_signal(signum)
        stdout, stderr = process.communicate(timeout=240)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)


def decisions_logged(run_dir: Path) -> list[int]:
    with open(run_dir / "progress.csv", newline="") as file:
        return [int(float(row["time/total_timesteps"])) for row in csv.DictReader(file)]


def test_ctrl_c_saves_a_checkpoint_evaluates_and_resumes(tmp_path):
    """Ctrl-C (SIGINT to the group, subprocess workers included) -> one line, status 130, a
    checkpoint; the interrupted run evaluates at that checkpoint; --resume finishes it."""
    out = tmp_path / "run"
    done = interrupt(out, signal.SIGINT, "subproc")
    assert done.returncode == 128 + signal.SIGINT, done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("train_ego_ppo.py: stopped by SIGINT; checkpoint ")
    assert f"--resume {out}" in last
    saved = Path(last.split("checkpoint ")[1].split(";")[0])
    assert saved.is_file() and not (out / "final_model.zip").exists()
    assert not list(saved.parent.glob(".*partial*"))  # every file renamed into place
    stopped_at = int(saved.name.removeprefix("ppo_").removesuffix("_steps.zip"))
    assert stopped_at >= 64 and stopped_at % 64 == 0  # an update boundary
    assert (out / "training.png").stat().st_size > 0

    evaluated = run(
        "evaluate_ego.py", "--runs", out, "--trust-model", "--no-baselines", "--scenes", "1",
        "--seeds", "0", "--episode-steps", "5", "--guidance-steps", "2", "--out", tmp_path / "eval",
    )  # fmt: skip
    assert f"latest checkpoint, checkpoints/{saved.name}" in evaluated.stdout
    assert (tmp_path / "eval" / "results.md").is_file()

    total = stopped_at + 64
    resumed = run("train_ego_ppo.py", "--resume", out, "--total-timesteps", str(total))
    assert f"resuming {out} at {stopped_at} decisions" in resumed.stdout
    assert (out / "final_model.zip").is_file()
    logged = decisions_logged(out)
    assert logged == sorted(logged) and logged[-1] == total  # the kept rows, then the new ones
    with zipfile.ZipFile(out / "final_model.zip") as archive:
        assert json.loads(archive.read("data"))["num_timesteps"] == total


def test_sigterm_saves_a_checkpoint_with_one_line(tmp_path):
    done = interrupt(tmp_path / "run", signal.SIGTERM, "dummy")
    assert done.returncode == 128 + signal.SIGTERM, done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("train_ego_ppo.py: stopped by SIGTERM")


def test_resume_from_one_checkpoint_is_bit_for_bit(tmp_path):
    """Two resumes of the same checkpoint train the same weights (the episodes in flight
    are not saved, so neither is the uninterrupted run: policies.rl.checkpoints)."""
    import shutil

    import torch
    from stable_baselines3 import PPO

    first = tmp_path / "first"
    run("train_ego_ppo.py", *TINY, "--total-timesteps", "64", "--vec-env", "dummy", "--out", first)
    second = tmp_path / "second"
    shutil.copytree(first, second)
    for folder in (first, second):
        run("train_ego_ppo.py", "--resume", folder, "--total-timesteps", "192")
    weights = [PPO.load(f / "final_model.zip").policy.state_dict() for f in (first, second)]
    assert weights[0].keys() == weights[1].keys()
    assert all(torch.equal(weights[0][key], weights[1][key]) for key in weights[0])
    before = PPO.load(first / "checkpoints" / "ppo_64_steps.zip").policy.state_dict()
    assert not all(torch.equal(before[key], weights[0][key]) for key in before)  # it trained


def test_resume_refuses_changed_options_and_bad_paths(tmp_path):
    missing = subprocess.run(script("train_ego_ppo.py", "--resume", tmp_path / "nope"),
                             capture_output=True, text=True, cwd=ROOT, timeout=120)  # fmt: skip
    assert missing.returncode == 2
    assert (
        missing.stderr.strip()
        == f"train_ego_ppo.py: error: --resume {tmp_path / 'nope'}: no such run folder"
    )
    (tmp_path / "afile").write_text("")
    a_file = subprocess.run(script("train_ego_ppo.py", "--resume", tmp_path / "afile"),
                            capture_output=True, text=True, cwd=ROOT, timeout=120)  # fmt: skip
    assert a_file.returncode == 2 and "a file, not a run folder" in a_file.stderr
    run_dir = fake_run(tmp_path / "run")
    changed = subprocess.run(script("train_ego_ppo.py", "--resume", run_dir, "--n-steps", "7"),
                             capture_output=True, text=True, cwd=ROOT, timeout=120)  # fmt: skip
    assert changed.returncode == 2 and "--n-steps 7 (the run's: 512)" in changed.stderr


def test_training_refuses_a_folder_that_holds_a_run(tmp_path):
    """A second run into the same --out would mix its checkpoints with the first's (and
    --resume would then go on from the wrong weights): refused, with the way out."""
    run_dir = fake_run(tmp_path / "run")
    before = (run_dir / "options.json").read_text()
    again = subprocess.run(script("train_ego_ppo.py", *TINY, "--out", run_dir),
                           capture_output=True, text=True, cwd=ROOT, timeout=120)  # fmt: skip
    assert again.returncode == 2
    assert again.stderr.strip() == (
        f"train_ego_ppo.py: error: --out {run_dir} holds a trained run already: continue it "
        f"with --resume {run_dir}, or choose another --out"
    )
    assert (run_dir / "options.json").read_text() == before


def test_a_run_that_never_trained_is_not_a_run(tmp_path):
    """A start that failed before its first checkpoint (options.json alone) does not block
    the next try; an empty checkpoints folder neither; a folder with checkpoints but no
    options.json cannot be resumed, and the refusal says so."""
    (tmp_path / "a" / "checkpoints").mkdir(parents=True)
    (tmp_path / "a" / "options.json").write_text("{}")
    assert not run_begun(tmp_path / "a")
    make_run_folder(tmp_path / "a")
    (tmp_path / "a" / "checkpoints" / "ppo_64_steps.zip").write_bytes(b"")
    assert run_begun(tmp_path / "a")
    with pytest.raises(RunError, match="continue it with --resume"):
        make_run_folder(tmp_path / "a")
    (tmp_path / "a" / "options.json").unlink()
    with pytest.raises(RunError, match="trained run already: remove it, or choose another"):
        make_run_folder(tmp_path / "a")


@pytest.mark.parametrize(
    ("script", "argv", "message"),
    [
        ("train", "--episode-steps -1", "--episode-steps must be an int >= 1, got -1"),
        ("train", "--scenes -4", "--scenes must be an int >= 1, got -4"),
        ("train", "--scenes 40", "--scenes: train has 35 scenes, got 40"),
        ("train", "--base-planner lan", "--base-planner must be one of ('none', 'idm', 'lane')"),
        ("train", "--split test", "--split must be one of ('eval', 'train'), got 'test'"),
        ("train", "--target-end all", "--target-end must be one of ('others', 'ego')"),
        ("train", "--k-start -1", "--k-start must be an int >= 0, got -1"),
        ("train", "--guidance-steps -2", "--guidance-steps must be an int >= 0, got -2"),
        ("train", "--planning-interval 0.25", "--planning-interval: 0.25 s is not a positive"),
        ("train", "--lambda-adv-end -1", "--lambda-adv-start and --lambda-adv-end must be >= 0"),
        ("train", "--ramp-fraction 2", "--ramp-fraction must be in [0, 1], got 2.0"),
        ("train", "--learning-rate -1", "--learning-rate must be a finite number > 0"),
        ("train", "--gamma 1.5", "--gamma must be a finite number in (0, 1], got 1.5"),
        ("train", "--log-std-init nan", "--log-std-init must be a finite number, got nan"),
        ("train", "--target-speed 0", "--target-speed must be a finite number > 0"),
        ("evaluate", "--no-baselines", "nothing to evaluate: give --runs or --oracle"),
        ("evaluate", "--seeds 0,x", "--seeds must be comma-separated ints >= 0 (e.g. 0,1,2)"),
        ("evaluate", "--seeds -1", "--seeds must be comma-separated ints >= 0"),
        ("evaluate", "--seeds 0,0", "--seeds must be distinct, got [0, 0]"),
        ("evaluate", "--episode-steps -5", "--episode-steps must be an int >= 1, got -5"),
        ("evaluate", "--scenes 0", "--scenes must be an int >= 1, got 0"),
        ("evaluate", "--k -1", "--k must be an int >= 0, got -1"),
        ("evaluate", "--guidance-steps -1", "--guidance-steps must be an int >= 0, got -1"),
        ("evaluate", "--planning-interval 9", "--planning-interval: 9.0 s exceeds the plan"),
    ],
)
def test_bad_options_are_one_line_naming_the_flag(script, argv, message, tmp_path, capsys):
    """Checked before anything runs or is written: no output folder is left behind."""
    name = "train_ego_ppo" if script == "train" else "evaluate_ego"
    with pytest.raises(SystemExit) as exit_info:
        load_script(f"examples/{name}.py").main([*argv.split(), "--out", str(tmp_path / "o")])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "o").exists()


def test_evaluation_seeds_take_commas_or_spaces():
    options = load_script("examples/evaluate_ego.py").Options
    assert options(seeds="0,1, 2").seed_list() == options(seeds="0 1 2").seed_list() == [0, 1, 2]


def fake_run(folder: Path, model: bytes = b"not a pickle") -> Path:
    """A run folder with options.json and model files whose 'data' member is ``model``."""
    folder.mkdir(parents=True)
    (folder / "options.json").write_text(json.dumps({"seed": 0, "n_steps": 512}))
    for name in ("initial_model.zip", "final_model.zip"):
        with zipfile.ZipFile(folder / name, "w") as archive:
            archive.writestr("data", model)
    return folder


def evaluate_main():
    """``examples/evaluate_ego.py``'s ``main``."""
    return load_script("examples/evaluate_ego.py").main


def test_reward_options_reach_the_env():
    train = load_script("examples/train_ego_ppo.py")
    reward = train.env_config(train.Options(speed_reward=0.2, target_speed=10.0)).env.reward
    assert (reward.speed, reward.target_speed, reward.collision) == (0.2, 10.0, -10.0)
    with pytest.raises(ValueError, match=r"--target-speed must be a finite number > 0, got 0.0"):
        train.Options(target_speed=0.0)


def test_find_model_takes_folders_and_files_with_or_without_zip(tmp_path):
    run_dir = fake_run(tmp_path / "run")
    assert find_model(run_dir).model == run_dir / "final_model.zip"
    for entry in (run_dir / "final_model", run_dir / "final_model.zip"):
        found = find_model(entry)
        assert found.model == run_dir / "final_model.zip" and found.run == run_dir
    assert find_model(run_dir, "initial_model.zip").model == run_dir / "initial_model.zip"
    (run_dir / "final_model.zip").unlink()
    (run_dir / "checkpoints").mkdir()
    for steps in (64, 128):
        (run_dir / "checkpoints" / f"ppo_{steps}_steps.zip").write_bytes(
            (run_dir / "initial_model.zip").read_bytes()
        )
    found = find_model(run_dir)  # interrupted: the latest checkpoint, said so
    assert found.model.name == "ppo_128_steps.zip" and "ppo_128_steps.zip" in found.note
    assert find_model(run_dir / "checkpoints" / "ppo_64_steps").run == run_dir
    with pytest.raises(RunError, match="--model checkpoints/ppo_9_steps: .* does not exist"):
        find_model(run_dir, "checkpoints/ppo_9_steps")


@pytest.mark.parametrize(
    ("make", "args", "message"),
    [
        (None, ["--runs", "{tmp}/nope"], "--runs {tmp}/nope: no such run folder or model file"),
        (None, ["--runs", "{tmp}"], "--runs {tmp}: not a training run folder (no options.json"),
        ("run", ["--runs", "{tmp}/run", "--model", "ppo_9"],
         "--model ppo_9: {tmp}/run/ppo_9.zip does not exist"),
        ("run", ["--runs", "{tmp}/run/options.json"],
         "--runs {tmp}/run/options.json: not a stable-baselines3 model file (not a zip file)"),
        ("run", ["--runs", "{tmp}/run/final_model.zip"],
         "--runs {tmp}/run/final_model.zip: cannot load"),
        ("loose", ["--runs", "{tmp}/loose.zip"], "no options.json beside the model"),
        (None, ["--combine", "{tmp}/results.json"], "--combine {tmp}/results.json: no such file"),
        (None, ["--data", "{tmp}/scenes"], "--data: "),
        ("file", ["--out", "{tmp}/afile"], "--out: {tmp}/afile exists and is not a folder"),
    ],
)  # fmt: skip
def test_every_wrong_path_is_one_line_naming_the_argument(tmp_path, capsys, make, args, message):
    """Before any episode runs: an ``--out`` that cannot be a folder is refused up front."""
    if make == "run":
        fake_run(tmp_path / "run")
    elif make == "file":
        (tmp_path / "afile").write_text("")
    elif make == "loose":
        with zipfile.ZipFile(tmp_path / "loose.zip", "w") as archive:
            archive.writestr("data", b"{}")
    argv = ["--trust-model", "--out", str(tmp_path / "out")]
    argv += [arg.format(tmp=tmp_path) for arg in args]
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main()(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("evaluate_ego.py: error: ")
    assert message.format(tmp=tmp_path) in err


def test_planners_picks_the_baselines(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main()(["--planners", "mpc"])
    assert exit_info.value.code == 2
    assert "--planners: unknown baseline(s) ['mpc']" in capsys.readouterr().err
    out = tmp_path / "out"
    evaluate_main()(
        ["--planners", "lane_keeping", "--nominal", "idm", "--scenes", "1", "--seeds", "0",
         "--episode-steps", "5", "--guidance-steps", "2", "--out", str(out)]
    )  # fmt: skip
    rows = json.loads((out / "results.json").read_text())["summary"]
    assert {row["planner"] for row in rows} == {"lane_keeping"} and len(rows) == 2


def test_nominal_traffics_and_recorded_scenes(tmp_path, capsys):
    """``--nominal`` takes several traffics (log replay among them) and ``--data`` a folder
    of scenes instead of the shipped bank: one row per (planner, traffic)."""
    from riskflow_env.scenarios import save_scenario, shipped_bank

    with pytest.raises(SystemExit) as exit_info:
        evaluate_main()(["--nominal", "generator,log"])
    assert exit_info.value.code == 2
    assert "--nominal must be a comma-separated list of" in capsys.readouterr().err

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for scenario in shipped_bank("eval")[:2]:
        save_scenario(scenario, scenes / f"{scenario.name}.npz")
    out = tmp_path / "out"
    evaluate_main()(
        ["--planners", "lane_keeping", "--nominal", "replay,idm", "--data", str(scenes),
         "--scenes", "2", "--seeds", "0", "--episode-steps", "5", "--guidance-steps", "2",
         "--target", "ego", "--out", str(out)]
    )  # fmt: skip
    content = json.loads((out / "results.json").read_text())
    rows = content["summary"]
    assert [row["traffic"] for row in rows] == ["riskflow K=5 ego", "idm", "replay"]
    assert all(row["ego_collision_rate"]["n"] == 2 for row in rows)
    assert len(content["episodes"]["scenes"]) == 2  # what --combine checks for overlap
    assert content["episodes"]["seeds"] == {"lane_keeping": [0]}


def test_combine_refuses_masked_and_raw_egos_together(tmp_path, capsys):
    """``--combine`` pools rows of the same name: not those of egos that chose their
    maneuvers with the action mask and without it."""
    entry = {"value": 0.1, "low": 0.0, "high": 0.2, "n": 10}
    metrics = ("ego_collision_rate", "ego_offroad_rate", "ego_failure_rate",
               "avoidable_failure_rate", "progress", "time_to_first_ego_collision")  # fmt: skip
    row = {"planner": "ppo", "traffic": "riskflow K=5"} | dict.fromkeys(metrics, entry)
    files = []
    for mask in (True, False):
        path = tmp_path / f"{mask}.json"
        content = {"summary": [row], "per_run": [], "paired": [], "mask_actions": mask}
        path.write_text(json.dumps(content))
        files.append(str(path))
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main()(["--combine", ",".join(files), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "with and without the action mask" in err
    evaluate_main()(["--combine", files[0], "--out", str(tmp_path / "out")])
    assert json.loads((tmp_path / "out" / "results.json").read_text())["mask_actions"] is True
