"""``examples/transfer_experiment.py`` end to end on a tiny budget (subprocess, as a user
runs it): three egos trained against three traffics, evaluated on shipped and recorded
scenes, the report; a second call reuses everything."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.samples import SCENARIONET_DIR, require_samples
from tests.scripts import load_script

pytest.importorskip("stable_baselines3", reason="the rl extra is not installed")

ROOT = Path(__file__).resolve().parents[2]
TRAIN = (
    "--total-timesteps 64 --num-envs 2 --n-steps 32 --batch-size 64 --n-epochs 1 "
    "--scenes 3 --episode-steps 20 --guidance-steps 2"
)


def run(*args: str | Path) -> subprocess.CompletedProcess:
    command = [sys.executable, str(ROOT / "examples" / "transfer_experiment.py"), *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=600)


@pytest.mark.slow
def test_pipeline_trains_three_egos_evaluates_them_and_reuses_its_work(tmp_path):
    require_samples()
    out = tmp_path / "transfer"
    common = ("--out", out, "--seeds", "3", "--scenes", "2", "--eval-seeds", "0",
              "--episode-steps", "20", "--data", SCENARIONET_DIR, "--data-scenes", "1")  # fmt: skip
    first = run(*common, "--train-args", TRAIN)
    assert first.returncode == 0, first.stderr[-3000:]

    # each ego trained against its own traffic, with the same seed and budget
    options = {
        name: json.loads((out / name / "seed3" / "options.json").read_text())
        for name in ("adversary", "unguided", "idm")
    }
    assert options["adversary"]["traffic"] == "riskflow" and options["adversary"]["k_end"] == 5
    assert options["unguided"]["traffic"] == "riskflow" and options["unguided"]["k_end"] == 0
    assert options["idm"]["traffic"] == "idm"
    assert {o["seed"] for o in options.values()} == {3}
    assert {o["total_timesteps"] for o in options.values()} == {64}
    assert {o["target_end"] for o in options.values()} == {"ego"}

    report = json.loads((out / "transfer.json").read_text())
    episodes = {"generator": 2, "adversary": 2, "replay (data)": 1, "generator (data)": 1,
                "adversary (data)": 1}  # fmt: skip
    cells = {(row["traffic"], row["trained_against"]): row for row in report["rows"]}
    assert set(cells) == {(t, n) for t in episodes for n in options}
    for (traffic, _), row in cells.items():
        assert row["ego_collision_rate"]["n"] == episodes[traffic]
        assert 0 <= row["ego_collision_rate"]["value"] <= 1
        assert row["progress"]["value"] > 0
    pairs = {(pair["traffic"], pair["against"]): pair for pair in report["paired"]}
    assert set(pairs) == {(t, n) for t in episodes for n in ("unguided", "idm")}
    assert all(pair["n"] == episodes[t] for (t, _), pair in pairs.items())
    assert "Paired, same episodes" in (out / "transfer.md").read_text()

    saved = json.loads((out / "episodes" / "idm-seed3.json").read_text())
    assert saved["settings"]["eval_seeds"] == [0] and saved["settings"]["mask_actions"]
    assert [tuple(e[:2]) for e in saved["episodes"]["generator"]] == [
        (name, 0) for name in saved["settings"]["scenes"]["shipped"]
    ]

    # a second call trains nothing and evaluates nothing: it needs --trust-model to load
    # models it did not train, and reads the saved outcomes
    refused = run(*common)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1].endswith("docs/reference/security.md)")
    again = run(*common, "--trust-model")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "train_ego_ppo.py" not in again.stdout
    assert json.loads((out / "transfer.json").read_text()) == report

    # a run stopped after its last checkpoint, before its final model: resumed, it gets
    # the final model from that checkpoint, and its saved evaluation still counts
    (out / "idm" / "seed3" / "final_model.zip").unlink()
    resumed = run(*common, "--trust-model")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "--resume" in resumed.stdout and (out / "idm" / "seed3" / "final_model.zip").is_file()
    assert json.loads((out / "transfer.json").read_text()) == report


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--seeds", "1,1"), "--seeds must be distinct, got [1, 1]"),
        (("--seeds", "-1"), "--seeds must be comma-separated ints >= 0"),
        (("--eval-seeds", "a"), "--eval-seeds must be comma-separated ints >= 0"),
        (("--train-args", "--traffic riskflow"), "--train-args may not set ['--traffic']"),
        (("--train-args", "--n-steps '8"), "--train-args: No closing quotation"),
    ],
)
def test_options_are_checked_before_anything_runs(args, message, tmp_path, capsys):
    """Each wrong option is refused with its name, before a folder is made (``main`` in
    this process: the subprocess test above runs the script as a user does)."""
    script = load_script("examples/transfer_experiment.py")
    with pytest.raises(SystemExit) as exit_info:
        script.main(["--out", str(tmp_path / "transfer"), *args])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "transfer").exists()
