"""``riskflow-data``: deterministic, worker-count independent, resumable banks."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from riskflow_env.folder_lock import FolderLock
from riskflow_env.scenarios import load_bank
from riskflow_env.scenarios.cli import GenerateOptions, generate, main
from tests.riskflow_env.scenarios.scenarionet_datasets import toy_descriptions, write_dataset
from tests.samples import COMMONROAD_DIR, require_commonroad


def _tiny(out, workers: int = 1, **changes) -> GenerateOptions:
    fields = dict(
        out=out, families=("u-turn", "merge"), scenes=2, seed=7, workers=workers, future_steps=10
    )
    fields.update(changes)
    return GenerateOptions(**fields)


def _files(directory) -> dict[str, bytes]:
    return {
        str(path.relative_to(directory)): path.read_bytes()
        for path in sorted(directory.rglob("*"))
        if path.is_file()
    }


def test_the_documented_command_makes_the_shipped_bank_again(tmp_path):
    """``riskflow-data generate --split eval --seed 0`` (docs/how-to/scenario-data.md): its
    first scenes are the shipped ones, to float rounding (a scene depends on the seed and
    its index only)."""
    import numpy as np

    from riskflow_env.scenarios import shipped_bank

    generate(GenerateOptions(out=tmp_path, scenes=2, split="eval", seed=0))
    for made, shipped in zip(load_bank(tmp_path), shipped_bank("eval"), strict=False):
        assert made.name == shipped.name
        assert made.states.shape == shipped.states.shape
        np.testing.assert_allclose(made.states, shipped.states, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(made.valid, shipped.valid)


@pytest.mark.reliability
def test_one_or_two_workers_write_identical_files(tmp_path):
    generate(_tiny(tmp_path / "one", workers=1))
    generate(_tiny(tmp_path / "two", workers=2))
    one, two = _files(tmp_path / "one"), _files(tmp_path / "two")
    assert sorted(one) == sorted(two)
    assert {"00000-u-turn.npz", "00001-merge.npz", "riskflow-data.json"} <= set(one)
    assert sum(name.startswith("maps/") for name in one) == 2  # one map per family
    assert one == two
    bank = load_bank(tmp_path / "one")
    assert [scene.family for scene in bank.scenarios] == ["u-turn", "merge"]
    assert all(scene.future_steps == 10 for scene in bank.scenarios)


@pytest.mark.reliability
def test_resume_skips_complete_scenes_and_redoes_missing_ones(tmp_path):
    out = tmp_path / "bank"
    assert generate(_tiny(out))["written"] == 2
    before = _files(out)
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    assert generate(_tiny(out)) | {"seconds": 0} == {
        "written": 0,
        "skipped": 2,
        "seconds": 0,
        "per_minute": 0.0,
    }
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == stamps
    (out / "00001-merge.npz").unlink()
    (out / ".00001-merge.npz.999.tmp").write_bytes(b"interrupted write")
    result = generate(_tiny(out, scenes=3))  # also extends the bank
    assert (result["written"], result["skipped"]) == (2, 1)
    after = _files(out)
    assert {name: after[name] for name in before} == before
    assert "00002-u-turn.npz" in after and not list(out.glob(".*.tmp"))


@pytest.mark.reliability
def test_resume_with_other_settings_is_refused(tmp_path):
    generate(_tiny(tmp_path, scenes=1))
    with pytest.raises(ValueError, match="other settings .seed: 7 there, 8 now.: use another"):
        generate(_tiny(tmp_path, scenes=1, seed=8))


def test_command_line(tmp_path, capsys):
    out = tmp_path / "bank"
    argv = ["generate", "--families", "u-turn", "--scenes", "1", "--out", str(out)]
    assert main([*argv, "--seed", "3", "--workers", "1", "--future-steps", "10"]) == 0
    assert "scenes/min" in capsys.readouterr().out
    assert main(["info", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "1 scenes" in printed and "u-turn" in printed and "split train" in printed
    with pytest.raises(SystemExit):
        main(["generate", "--families", "nowhere", "--out", str(out)])


def test_stop_share_is_recorded_only_when_used(tmp_path):
    """Banks made before ``--stop-share`` existed keep resuming: the key is absent at 0."""
    assert "stop_share" not in _tiny(tmp_path / "a").settings()
    assert _tiny(tmp_path / "b", stop_share=0.2).settings()["stop_share"] == 0.2


@pytest.mark.reliability
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seed", "-1"], "argument --seed: expected an int >= 0, got '-1'"),
        (["--scenes", "0"], "argument --scenes: expected an int >= 1, got '0'"),
        (["--workers", "0"], "argument --workers: expected an int >= 1, got '0'"),
        (["--future-steps", "x"], "argument --future-steps: expected an int >= 1, got 'x'"),
        (["--stop-share", "1.5"], "argument --stop-share: expected a number in [0, 1], got '1.5'"),
        (["--workers", "1000"], "--workers must be an int in [1, 256], got 1000"),  # no OOM
        (["--future-steps", "100000000"], "--future-steps must be an int in [1, 19969]"),
    ],
)
def test_bad_numbers_are_usage_errors_before_anything_is_written(args, message, tmp_path, capsys):
    """Issue 19: `--seed -1` wrote the manifest, then died with a traceback."""
    out = tmp_path / "bank"
    with pytest.raises(SystemExit) as exit_info:
        main(["generate", "--families", "u-turn", "--scenes", "1", "--out", str(out), *args])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.reliability
def test_info_of_a_folder_without_scenes_is_an_error(tmp_path, capsys):
    """`info` of an empty folder printed "0 scenes" and exited 0; of a ScenarioNet folder
    with a broken scenario file it names the file."""
    with pytest.raises(SystemExit) as exit_info:
        main(["info", str(tmp_path)])
    assert exit_info.value.code == 2
    assert f"no scenario files (*.npz) in {tmp_path}" in capsys.readouterr().err
    (tmp_path / "sd_a.pkl").write_bytes(b"")
    with pytest.raises(SystemExit) as exit_info:
        main(["info", str(tmp_path)])
    assert exit_info.value.code == 2
    assert f"{tmp_path / 'sd_a.pkl'}: not a readable data pickle" in capsys.readouterr().err


def test_info_of_scenarionet_folders(tmp_path, capsys):
    """Per source dataset, from the summary or (no summary) from each file's metadata."""
    indexed = tmp_path / "indexed"
    names = write_dataset(indexed, toy_descriptions(3) + toy_descriptions(1, "waymo"))
    assert main(["info", str(indexed)]) == 0
    printed = capsys.readouterr().out
    assert f"{indexed}: 4 ScenarioNet scenes" in printed
    assert re.search(r"nuscenes +3 ", printed) and re.search(r"waymo +1 ", printed)
    (indexed / f"{indexed.name}_0" / names[0]).unlink()
    assert main(["info", str(indexed)]) == 0
    assert "3 ScenarioNet scenes" in (out := capsys.readouterr().out) and "1 listed" in out

    bare = tmp_path / "bare"  # the scenario files alone, as copied from a converter folder
    bare.mkdir()
    for path in (indexed / f"{indexed.name}_1").glob("sd_*.pkl"):
        shutil.copy(path, bare / path.name)
    assert main(["info", str(bare)]) == 0
    printed = capsys.readouterr().out
    assert f"{bare}: 2 ScenarioNet scenes" in printed

    for name in names[1:]:  # none left: an error, not "0 scenes"
        (indexed / f"{indexed.name}_{0 if name in names[:2] else 1}" / name).unlink()
    with pytest.raises(SystemExit) as exit_info:
        main(["info", str(indexed)])
    assert exit_info.value.code == 2
    assert "none of the 4 scenario files its summary lists is present" in capsys.readouterr().err


def test_info_of_commonroad_scenarios(capsys):
    """Counted without commonroad-io (the files are not parsed)."""
    files = require_commonroad()
    assert main(["info", str(COMMONROAD_DIR)]) == 0
    printed = capsys.readouterr().out
    assert f"{COMMONROAD_DIR}: {len(files)} CommonRoad scenarios (.xml)" in printed


@pytest.mark.reliability
def test_out_that_is_a_file_is_a_usage_error(tmp_path, capsys):
    existing = tmp_path / "bank.txt"
    existing.write_text("keep me")
    with pytest.raises(SystemExit) as exit_info:
        main(["generate", "--families", "u-turn", "--scenes", "1", "--out", str(existing)])
    assert exit_info.value.code == 2
    error = f"riskflow-data generate: error: --out: {existing} exists and is not a folder"
    assert error in capsys.readouterr().err  # the subcommand named
    assert existing.read_text() == "keep me"


@pytest.mark.reliability
@pytest.mark.parametrize("command", ["generate", "export"])
def test_out_the_system_refuses_is_a_usage_error(command, tmp_path, monkeypatch, capsys):
    """A read-only or virtual file system (``--out /proc/bank``): one line naming --out."""

    def refuse(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    if command == "export":  # a readable input: export reads every input before --out
        from riskflow_env.scenarios import save_scenario, shipped_bank

        save_scenario(shipped_bank("eval")[0], tmp_path / "scene.npz")
    monkeypatch.setattr(Path, "mkdir", refuse)
    args = ["--families", "u-turn", "--scenes", "1"] if command == "generate" else [
        str(tmp_path / "scene.npz"), "--format", "scenarionet"
    ]  # fmt: skip
    with pytest.raises(SystemExit) as exit_info:
        main([command, *args, "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert "--out: cannot make the folder" in capsys.readouterr().err


@pytest.mark.reliability
@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"seed": -1}, "seed must be an int >= 0"),
        ({"scenes": True}, "scenes must be an int, got True"),
        ({"workers": 0}, "workers must be an int in \\[1, 256\\]"),
        ({"split": "test"}, "split must be one of"),
        ({"families": ("moon",)}, "families must be a non-empty subset"),
        ({"stop_share": -0.1}, "stop_share must be a number in"),
    ],
)
def test_generate_options_are_validated(changes, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        _tiny(tmp_path / "bank", **changes)
    assert not (tmp_path / "bank").exists()


@pytest.mark.reliability
def test_scenes_beyond_a_previous_run_are_made_in_full(tmp_path):
    """`--scenes N` means indices 0 .. N-1, generated procedurally: a bank of 1 scene
    grows to 3, never silently fewer."""
    out = tmp_path / "bank"
    assert generate(_tiny(out, scenes=1))["written"] == 1
    assert generate(_tiny(out, scenes=3)) | {"seconds": 0, "per_minute": 0} == {
        "written": 2, "skipped": 1, "seconds": 0, "per_minute": 0
    }  # fmt: skip
    assert len(load_bank(out).scenarios) == 3


def _children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is ``pid`` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.reliability
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_die_with_a_killed_parent(tmp_path):
    """Issue 19: after kill -9 of `generate --workers 2` the workers kept writing, then
    slept forever. Now they end within seconds and write nothing more."""
    out = tmp_path / "bank"
    command = [sys.executable, "-m", "riskflow_env.scenarios.cli", "generate", "--out", str(out)]
    command += ["--families", "u-turn", "--scenes", "40", "--workers", "2", "--future-steps", "10"]
    parent = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 240
        while not list(out.glob("0*.npz")) and time.monotonic() < deadline:
            assert parent.poll() is None, "riskflow-data ended early"
            time.sleep(0.2)
        workers = _children(parent.pid)
        assert len(workers) >= 2, "no worker processes found"
    finally:
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
    deadline = time.monotonic() + 20
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers), "a worker outlived its parent"
    written = sorted(path.name for path in out.glob("0*.npz"))
    time.sleep(1.0)
    assert sorted(path.name for path in out.glob("0*.npz")) == written
    assert len(written) < 40


@pytest.mark.reliability
def test_second_generate_into_one_bank_is_refused(tmp_path):
    """A second run deleted the first one's temporary files; now it exits naming the pid."""
    out = tmp_path / "bank"
    with FolderLock(out):
        with pytest.raises(SystemExit, match=rf"being written by another run \(pid {os.getpid()}"):
            generate(_tiny(out, scenes=1))
        assert not (out / "riskflow-data.json").exists()
    generate(_tiny(out, scenes=1))  # released: the bank is written
    assert (out / "00000-u-turn.npz").is_file()


KILLED_GENERATE = """
import os, signal, sys
from riskflow_env.scenarios import cli

real_replace, renamed = os.replace, []


def replace(source, target):  # kill -9 just before the third scene file appears
    if os.path.dirname(target) == sys.argv[1] and str(target).endswith(".npz"):  # no manifest
        renamed.append(target)
        if len(renamed) == 3:
            os.kill(os.getpid(), signal.SIGKILL)
    real_replace(source, target)


os.replace = replace
cli.main(["generate", "--out", sys.argv[1], *sys.argv[2:]])
"""


@pytest.mark.reliability
def test_kill_9_then_resume_gives_the_uninterrupted_bank(tmp_path):
    """Issue 19 deliverable 6: `riskflow-data generate` killed -9 while writing a scene
    (its temporary file on disk), then the same command again: the bank is the one an
    uninterrupted run writes, byte for byte."""
    args = ["--families", "u-turn", "merge", "--scenes", "5", "--seed", "7", "--workers", "1"]
    args += ["--future-steps", "10"]
    killed = tmp_path / "killed"
    child = subprocess.run(
        [sys.executable, "-c", KILLED_GENERATE, str(killed), *args],
        capture_output=True,
        text=True,
        timeout=600,  # a hang guard only: the machine may be loaded
    )
    assert child.returncode == -signal.SIGKILL, child.stderr[-2000:]
    assert len(list(killed.glob("0*.npz"))) == 2
    assert list(killed.glob(".*.tmp"))  # the scene being written when killed
    assert main(["generate", "--out", str(killed), *args]) == 0
    reference = tmp_path / "reference"
    assert main(["generate", "--out", str(reference), *args]) == 0
    killed_files, reference_files = _files(killed), _files(reference)
    for files in (killed_files, reference_files):
        files.pop("writer.lock")  # holds the last writer's pid
    assert sorted(killed_files) == sorted(reference_files)
    assert killed_files == reference_files
