"""``riskflow-stress`` as a user runs it: a planner from a file or an import path, the run
end to end on two scenes (its files, the same results with two workers), bad ``--planner``
errors, a failure replayed bit for bit with the user's planner, and ``compare``."""

from __future__ import annotations

import json
import re
import textwrap

import numpy as np
import pytest

from policies.planners import ConstantVelocityPlanner, IDMPlanner
from policies.stress import load_planner, load_replay, replay, riskflow_stress
from policies.stress.cli import RunOptions, main
from policies.stress.planner_spec import PlannerSpecError, spec_of
from riskflow_env.scenarios import load_scenario, save_scenario, shipped_bank
from tests.policies.stress.planner_sources import RECKLESS

pytestmark = pytest.mark.integration

# A user's planner file: ``reckless`` (``planner_sources.RECKLESS``) and ``Cautious``, a class
# with state that ``reset`` clears.
PLANNER_FILE = RECKLESS + textwrap.dedent(
    """
    class Cautious:
        def reset(self, view):
            self.calls = 0

        def __call__(self, observation, view):
            self.calls += 1
            return reckless(observation, view) if self.calls > 3 else np.zeros(2)

    def make_cautious():
        return Cautious()

    SPEED = 12.0
    """
)
STEPS = 30
SCENES = (7, 5)  # busy highway and exit scenes of the shipped evaluation bank


@pytest.fixture(scope="module")
def planner_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("user") / "user_planners.py"
    path.write_text(PLANNER_FILE)
    return path


@pytest.fixture(scope="module")
def scenes_dir(tmp_path_factory):
    """Two shipped scenes as a --data folder."""
    folder = tmp_path_factory.mktemp("scenes")
    bank = shipped_bank("eval")
    for index in SCENES:
        save_scenario(bank[index], folder / f"{bank[index].name}.npz")
    return folder


@pytest.fixture(scope="module")
def run(planner_file, scenes_dir, tmp_path_factory):
    """The CLI end to end: the file planner on two scenes, two workers."""
    out = tmp_path_factory.mktemp("run")
    main([
        "--planner", f"{planner_file}:reckless", "--data", str(scenes_dir), "--scenes", "2",
        "--steps", str(STEPS), "--workers", "2", "--gifs", "1", "--no-progress",
        "--out", str(out),
    ])  # fmt: skip
    return out


def test_end_to_end_writes_summary_reports_and_replays(run):
    summary = json.loads((run / "summary.json").read_text())
    for key in ("ego_collision_rate", "avoidable_share", "standing_strike_share",
                "non_ego_contact_share"):  # fmt: skip
        assert set(summary[key]) == {"value", "low", "high", "n"}
    assert "value" in summary["attackers_at_impact"] and summary["types"] and summary["families"]
    assert summary["options"]["steps"] == STEPS and summary["options"]["workers"] == 2
    rows = summary["per_episode"]
    assert [row["seed"] for row in rows] == [0, 0] and len(rows) == 2
    assert rows[0]["failures"], "the reckless planner collides on the busy highway scene"
    lines = (run / "episodes.jsonl").read_text().splitlines()
    assert sorted(json.loads(line)["scene"] for line in lines) == sorted(r["scene"] for r in rows)
    for row in rows:
        assert (row["replay"] is not None) == bool(row["failures"])
        if row["replay"]:
            assert load_scenario(run / row["replay"]).name == row["scene"]
    report = (run / "report.md").read_text()
    assert "Ego collisions by type" in report and "by road family" in report
    assert "time to the first ego collision" in report and "gifs/" in report
    page = (run / "report.html").read_text()
    assert page.count("data:image/gif;base64,") == 1 and len(summary["gifs"]) == 1
    assert summary["gifs"][0]["reproduced"]
    # the report's replay command runs as printed, where the stress test ran
    command = next(line for line in report.splitlines() if line.startswith("riskflow-stress "))
    assert command.split()[2] == str(run / summary["gifs"][0]["gif"]).replace(
        "gifs/", "failures/"
    ).replace(".gif", ".npz")
    main(command.split()[1:])


def test_two_workers_give_the_results_of_one(run, planner_file, scenes_dir):
    loaded = load_planner(f"{planner_file}:reckless")
    one = riskflow_stress(  # numpy ints, as from a user's loop, are counts; one seed an int
        loaded, np.int64(2), 0, data=scenes_dir, steps=np.int64(STEPS), workers=1,
        progress=False,
    )  # fmt: skip
    two = json.loads((run / "summary.json").read_text())
    for mine, theirs in zip(one.summary["per_episode"], two["per_episode"], strict=True):
        assert mine["scene"] == theirs["scene"]
        assert json.loads(json.dumps(mine["failures"])) == theirs["failures"]
    assert one.summary["ego_collision_rate"] == two["ego_collision_rate"]


def test_a_run_replaces_its_own_files_and_nothing_else(planner_file, scenes_dir, tmp_path):
    """docs/reference/formats.md: a previous run's failures go, a user's file stays."""
    (tmp_path / "failures").mkdir()
    (tmp_path / "failures" / "old_scene-seed3.npz").write_bytes(b"a previous run's")
    (tmp_path / "failures" / "important.npz").write_bytes(b"the user's")
    riskflow_stress(
        f"{planner_file}:reckless", 1, (0,), data=scenes_dir, steps=STEPS, gifs=0,
        progress=False, out=tmp_path,
    )  # fmt: skip
    assert not (tmp_path / "failures" / "old_scene-seed3.npz").exists()
    assert (tmp_path / "failures" / "important.npz").read_bytes() == b"the user's"


def test_replay_puts_the_user_planner_back_bit_for_bit(run, planner_file, capsys):
    summary = json.loads((run / "summary.json").read_text())
    file = run / next(row["replay"] for row in summary["per_episode"] if row["replay"])
    saved = load_replay(file)
    assert saved.meta["planner"] == f"{planner_file}:reckless" and saved.seed == 0
    again = replay(file, f"{planner_file}:reckless")  # a spec, as riskflow_stress takes
    assert again.recurred and again.identical and again.checkpoint_matches
    np.testing.assert_array_equal(again.analysed.record.states, saved.states)
    main(["replay", str(file)])  # the saved planner by default
    assert "RECURS" in capsys.readouterr().out
    other = replay(saved, ConstantVelocityPlanner())  # a "fixed" planner: a new episode
    assert not other.identical


def test_planner_from_a_file(planner_file):
    assert callable(load_planner(f"{planner_file}:reckless"))
    stateful = load_planner(f"{planner_file}:Cautious")  # a class: instantiated
    assert type(stateful).__name__ == "Cautious"
    assert type(load_planner(f"{planner_file}:make_cautious")).__name__ == "Cautious"
    assert spec_of(stateful).endswith("user_planners.py:Cautious")


def test_planner_by_import_path_and_name(tmp_path, monkeypatch):
    package = tmp_path / "acme_planners"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "drive.py").write_text(PLANNER_FILE)
    monkeypatch.syspath_prepend(str(tmp_path))
    planner = load_planner("acme_planners.drive:reckless")
    assert planner.__module__ == "acme_planners.drive"
    assert spec_of(planner) == "acme_planners.drive:reckless"
    assert isinstance(load_planner("policies.planners:IDMPlanner"), IDMPlanner)
    assert isinstance(load_planner("idm"), IDMPlanner)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("no_such_pkg.planners:plan", "no module named 'no_such_pkg'"),
        ("FILE:missing", "has no attribute 'missing'"),
        ("FILE:SPEED", "float object is not callable"),
        ("json:dumps", "cannot be called as planner(observation, view)"),
        ("nowhere/planner.py:plan", "no such file"),
        ("just_a_name", "expected a built-in name"),
        ("imd", "did you mean idm"),
        ("my_planner.py", "name the planner in it: my_planner.py:OBJECT, e.g. my_planner.py:plan"),
    ],
)
def test_bad_planner_errors_name_the_argument(spec, message, planner_file, tmp_path, capsys):
    spec = spec.replace("FILE", str(planner_file))
    with pytest.raises(PlannerSpecError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_planner(spec)
    with pytest.raises(SystemExit) as exit_info:
        main(["--planner", spec, "--scenes", "1", "--steps", "2", "--out", str(tmp_path)])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert f"--planner {spec!r}" in error and message in error


@pytest.mark.parametrize(
    ("planner", "message"),
    [
        ("nope", "--planner 'nope': expected a built-in name (idm, "),
        ("", "--planner '': expected a built-in name"),
        (None, "--planner None: expected a built-in name"),
        ("module:", "--planner 'module:': expected a built-in name"),
        ("imd", "--planner 'imd': expected a built-in name"),
    ],
)
def test_run_options_refuse_a_planner_of_no_form_when_built(planner, message):
    """The form alone (no import, no file read: the run loads the planner)."""
    with pytest.raises(PlannerSpecError, match="^" + re.escape(message)):
        RunOptions(planner=planner)
    assert RunOptions(planner="no_such_pkg.planners:plan").planner == "no_such_pkg.planners:plan"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--target", "ego2"], "--target must be one of ('others', 'ego'), got 'ego2'"),
        (["--k", "al"], "--k must be an int >= 0 or 'all', got 'al'"),
        (["--steps", "0"], "--steps must be an int >= 1"),
        (["--seeds", "0", "0"], "--seeds must be distinct, got [0, 0]"),
        (["--seeds", "-1"], "--seeds must be one or more ints in [0, 2**32), got [-1]"),
        (["--checkpoint", "nowhere.pt"], "--checkpoint: no such file 'nowhere.pt'"),
        (["--checkpoint", "TMP"], "--checkpoint: 'TMP' is a folder, not a file"),
        (["--checkpoint", "TMP/empty.pt"], "--checkpoint: cannot read generator checkpoint "
         "TMP/empty.pt: the file is empty or truncated (EOFError)"),
        (["--planning-interval", "-0.5"], "--planning-interval: -0.5 s is not a positive"),
        (["comparee", "idm", "idm"], "unknown command 'comparee': expected 'replay FILE'"),
        (["replay", "TMP"], "file: 'TMP' is a folder, not a replay file"),
        (["replay", "x.npz", "--video", "TMP"], "--video must end in one of ('.gif', "),
        (["replay", "x.npz", "--video", "TMP/empty.pt/x.gif"],
         "--video: TMP/empty.pt exists and is not a folder"),
    ],
)  # fmt: skip
def test_bad_options_name_the_argument(argv, message, tmp_path, capsys):
    """One line naming the argument, before any episode runs (no progress bar)."""
    (tmp_path / "empty.pt").write_bytes(b"")
    argv = [arg.replace("TMP", str(tmp_path)) for arg in argv]
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--out", str(tmp_path / "out")] if argv[0] != "replay" else argv)
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert message.replace("TMP", str(tmp_path)) in error and "episode" not in error


def test_compare_two_planners_paired(scenes_dir, planner_file, tmp_path, capsys):
    main([
        "compare", f"{planner_file}:reckless", "constant_velocity", "--data", str(scenes_dir),
        "--scenes", "2", "--steps", str(STEPS), "--gifs", "0", "--no-progress",
        "--out", str(tmp_path),
    ])  # fmt: skip
    table = json.loads((tmp_path / "compare.json").read_text())
    assert table["episodes"] == 2 and table["b"] == "constant_velocity"
    collisions = table["rows"][0]
    assert collisions["outcome"] == "ego collision rate" and 0 <= collisions["p_value"] <= 1
    assert collisions["a_only"] >= 1, "the reckless planner fails where constant velocity does not"
    assert [row["outcome"] for row in table["rows"][-2:]] == [
        "ego progress [m] (counter-metric)", "ego collisions per km (counter-metric)"
    ]  # fmt: skip
    printed = capsys.readouterr().out
    assert "McNemar" in printed and "runs: a-reckless/, b-constant_velocity/" in printed
    assert table["folders"] == {"a": "a-reckless", "b": "b-constant_velocity"}
    assert (tmp_path / "a-reckless" / "report.html").is_file()
    assert f"{tmp_path}/b-constant_velocity/" in printed  # the closing line names the runs


def test_compare_checks_both_planners_before_running_either(scenes_dir, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "idm", "nosuch", "--data", str(scenes_dir), "--out", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "PLANNER_B 'nosuch': expected a built-in name" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # no episode of a ran
    for b, error in (
        ("nonexist.py:plan", "PLANNER_B 'nonexist.py:plan': no such file"),
        ("policies.planners:no_such_planner", "has no attribute 'no_such_planner'"),
    ):  # well formed, but nothing to load: found before a's episodes too
        with pytest.raises(SystemExit) as exit_info:
            main(["compare", "idm", b, "--data", str(scenes_dir), "--out", str(tmp_path)])
        assert exit_info.value.code == 2 and error in capsys.readouterr().err
        assert not any(tmp_path.iterdir())
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "idm"])
    assert exit_info.value.code == 2
    assert "the following arguments are required: PLANNER_B" in capsys.readouterr().err


def test_ctrl_c_reports_the_episodes_that_finished(scenes_dir, tmp_path, monkeypatch, capsys):
    """Ctrl-C after the first episode: summary.json and the reports cover it, marked as
    interrupted, and the command ends with one line and status 130."""
    from policies.stress import runner

    real = runner._episodes

    def interrupted_after_one(*args):
        episodes = real(*args)
        yield next(episodes)
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "_episodes", interrupted_after_one)
    _interrupted_idm_run(scenes_dir, tmp_path)
    error = capsys.readouterr().err
    assert error.endswith(
        f"riskflow-stress: interrupted: 1 of 2 episodes finished; {tmp_path}/summary.json "
        "and the reports cover them (no GIF)\n"
    )
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["interrupted"] == {"episodes": 1, "planned": 2, "cause": "interrupted"}
    assert summary["episodes"] == 1
    assert "1 episode (interrupted: 1 of 2)" in (tmp_path / "report.md").read_text()
    assert len((tmp_path / "episodes.jsonl").read_text().splitlines()) == 1


def test_ctrl_c_inside_compiled_code_reports_the_episodes_that_finished(
    scenes_dir, tmp_path, monkeypatch, capsys
):
    """Ctrl-C inside a numba kernel surfaces as a SystemError around the KeyboardInterrupt:
    the episodes that finished are reported as for a plain Ctrl-C."""
    from policies.stress import runner

    real = runner._episodes

    def interrupted_in_numba(*args):
        episodes = real(*args)
        yield next(episodes)
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("compiled function raised") from None

    monkeypatch.setattr(runner, "_episodes", interrupted_in_numba)
    _interrupted_idm_run(scenes_dir, tmp_path)
    assert "interrupted: 1 of 2 episodes finished" in capsys.readouterr().err
    assert json.loads((tmp_path / "summary.json").read_text())["episodes"] == 1


def test_ctrl_c_while_drawing_the_gifs_keeps_the_reports(scenes_dir, tmp_path, monkeypatch, capsys):
    """Ctrl-C after the last episode, while the worst failures are re-run for their GIFs:
    summary.json and the reports, written before the GIFs, cover every episode."""
    from policies.stress import stress_test

    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(stress_test._Writer, "draw_worst", interrupted)
    _interrupted_idm_run(scenes_dir, tmp_path)
    assert capsys.readouterr().err.endswith(
        f"riskflow-stress: interrupted: while drawing the GIFs; {tmp_path}/summary.json and "
        "the reports cover all 2 episodes (no GIF)\n"
    )
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["episodes"] == 2 and summary["gifs"] == [] and "interrupted" not in summary
    assert (tmp_path / "report.md").is_file() and (tmp_path / "report.html").is_file()


def _interrupted_idm_run(scenes_dir, out) -> None:
    """``riskflow-stress`` with the IDM planner on two scenes, which must end as a Ctrl-C
    does (status 130)."""
    with pytest.raises(SystemExit) as exit_info:
        main([
            "--planner", "idm", "--data", str(scenes_dir), "--scenes", "2",
            "--steps", str(STEPS), "--no-progress", "--out", str(out),
        ])  # fmt: skip
    assert exit_info.value.code == 130
