"""A user error at a command line is one line on stderr and exit status 2; ``--debug``
shows the traceback instead (riskflow_env.cli_errors)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from policies.evaluation.cli import main as eval_main
from riskflow_env.cli_errors import (
    debug_requested,
    interrupt_of,
    message,
    require_extra,
    run_script,
    user_errors,
)
from riskflow_env.scenarios._npz import ScenarioFormatError
from riskflow_env.scenarios.cli import main as data_main


def test_a_user_error_is_one_line_and_status_2(capsys):
    with pytest.raises(SystemExit) as exit_info, user_errors("prog"):
        raise ScenarioFormatError("bank/s0.npz: not a readable .npz file\n(no zip record)")
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1
    assert error.startswith("prog: error: bank/s0.npz: not a readable .npz file (no zip record)")
    assert "--debug" in error


def test_debug_keeps_the_traceback_and_bugs_always_do():
    with pytest.raises(FileNotFoundError), user_errors("prog", debug=True):
        raise FileNotFoundError(2, "No such file or directory", "runs/x")
    with pytest.raises(KeyError), user_errors("prog"):
        raise KeyError("a bug, not a user error")


def test_ctrl_c_is_one_line_saying_what_is_kept_and_status_130(capsys):
    with pytest.raises(SystemExit) as exit_info, user_errors("prog", kept="the same run resumes"):
        raise KeyboardInterrupt("3 of 8 done")
    assert exit_info.value.code == 130
    assert capsys.readouterr().err == "\nprog: interrupted: 3 of 8 done; the same run resumes\n"
    with pytest.raises(SystemExit) as exit_info, user_errors("prog"):
        try:  # Ctrl-C inside a numba function: a SystemError raised while handling it
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("CPUDispatcher returned a result with an exception set") from None
    assert exit_info.value.code == 130 and capsys.readouterr().err == "\nprog: interrupted\n"
    with pytest.raises(KeyboardInterrupt), user_errors("prog", debug=True):
        raise KeyboardInterrupt
    with pytest.raises(SystemError), user_errors("prog"):
        raise SystemError("a bug, not an interrupt")


@pytest.mark.skipif(not hasattr(signal, "raise_signal") or os.name != "posix", reason="POSIX")
def test_sigterm_stops_as_ctrl_c_does_and_the_handler_comes_back(capsys):
    """What a scheduler or ``kill`` sends: one line, status 143, the body's own Ctrl-C
    handling (what is finished is kept); an ignored SIGTERM stays ignored."""
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as exit_info, user_errors("prog", kept="reports kept"):
        signal.raise_signal(signal.SIGTERM)
    assert exit_info.value.code == 143
    assert capsys.readouterr().err == "\nprog: interrupted: reports kept\n"
    assert signal.getsignal(signal.SIGTERM) is before
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with user_errors("prog"):
            signal.raise_signal(signal.SIGTERM)  # ignored: the body goes on
            assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before)


def test_an_interrupt_that_numba_wrapped_twice_is_found():
    interrupt = KeyboardInterrupt()
    inner = SystemError("returned a result with an exception set")
    inner.__cause__ = interrupt
    outer = SystemError("returned a result with an exception set")
    outer.__cause__ = inner
    assert interrupt_of(outer) is interrupt and interrupt_of(SystemError("bug")) is None


def test_messages_are_bounded_and_name_the_os_error():
    assert message(FileNotFoundError(2, "No such file", "a.npz")).startswith("FileNotFoundError")
    assert len(message(ValueError("x" * 10**6))) < 1100


def test_riskflow_eval_report_on_a_missing_folder(tmp_path, capsys):
    missing = tmp_path / "nothing"
    with pytest.raises(SystemExit) as exit_info:
        eval_main(["report", "--out", str(missing)])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert error.startswith("riskflow-eval report: error: ") and str(missing) in error
    assert "Traceback" not in error
    with pytest.raises(FileNotFoundError):
        eval_main(["report", "--out", str(missing), "--debug"])
    a_file = tmp_path / "results.txt"
    a_file.write_text("")
    with pytest.raises(SystemExit):
        eval_main(["report", "--out", str(a_file)])
    assert f"--out {a_file} is a file, not a results folder" in capsys.readouterr().err


def test_riskflow_data_info_on_a_broken_bank(tmp_path, capsys):
    bank = tmp_path / "bank"
    bank.mkdir()
    (bank / "s0.npz").write_bytes(b"not a zip file")
    with pytest.raises(SystemExit) as exit_info:
        data_main(["info", str(bank)])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert error.startswith("riskflow-data info: error: ") and "s0.npz" in error
    with pytest.raises(ScenarioFormatError):
        data_main(["info", str(bank), "--debug"])


def test_debug_is_recognised_as_argparse_reads_it():
    assert debug_requested(["--data", "d", "--deb"]) and debug_requested(["--debug"])
    assert not debug_requested(["--data", "d", "--steps", "2"])


def test_run_script_is_one_line_and_reads_debug_from_argv(capsys):
    def main():
        raise FileNotFoundError("no generator checkpoint at /nope")

    with pytest.raises(SystemExit) as exit_info:
        run_script("rollout.py", main, ["--checkpoint", "/nope"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.startswith("rollout.py: error: no generator checkpoint")
    with pytest.raises(FileNotFoundError):
        run_script("rollout.py", main, ["--checkpoint", "/nope", "--debug"])


def test_a_system_error_keeps_its_type(tmp_path, capsys):
    """The system's OSError (with an errno) is named; the library's own messages are not."""

    def main():
        open(tmp_path / "absent.txt")  # noqa: SIM115

    with pytest.raises(SystemExit):
        run_script("tool.py", main, [])
    assert "tool.py: error: FileNotFoundError: [Errno 2]" in capsys.readouterr().err


SCRIPTS_WITH_PATHS = [
    ("examples/rollout.py", ["--checkpoint", "/nope"], "--checkpoint: no generator checkpoint"),
    ("examples/rollout.py", ["--checkpoint", "README.md"], "--checkpoint: cannot read"),
    ("examples/rollout.py", ["--scenario", "docs"], "--scenario 'docs' is a folder"),
    ("examples/rollout.py", ["--scenario", "105"], "--scenario 105: the shipped bank"),
    ("examples/stress_test_planner.py", ["--planner", "nope.mod:x"], "no module named 'nope'"),
    ("examples/stress_test_planner.py", ["--data", "/nope"], "/nope does not exist"),
    ("benchmarks/failures_that_matter.py", ["--data", "/nope"], "/nope does not exist"),
    ("benchmarks/adversary_quality.py", ["--checkpoint", "/nope"], "checkpoint at /nope"),
    ("benchmarks/realism_diagnosis.py", ["--bank", "/nope"], "/nope does not exist"),
    ("benchmarks/traffic_realism.py", ["--bank", "/nope"], "/nope does not exist"),
    ("benchmarks/scenarionet_dataset.py", ["--data", "/nope"], "/nope does not exist"),
    ("benchmarks/eval_batched.py", ["--scenes", "1", "--out", "/proc/x"], "--out"),
    ("benchmarks/scenarionet_map_size.py", ["--files", "/nope.pkl", "--area", "50"], "/nope.pkl"),
]


@pytest.mark.reliability
@pytest.mark.parametrize(("script", "args", "expected"), SCRIPTS_WITH_PATHS)
def test_examples_and_benchmarks_name_a_bad_path_in_one_line(script, args, expected):
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(
        [sys.executable, str(root / script), *args],
        capture_output=True,
        text=True,
        cwd=root,
        timeout=300,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert done.stderr.startswith(f"{Path(script).name}: error: ") and expected in done.stderr


def test_a_missing_extra_is_one_line_naming_it():
    require_extra("x.py", "rl", "numpy.linalg")  # installed: nothing happens
    for module in ("no_such_package", "no_such_package.sub"):
        with pytest.raises(SystemExit) as exit_info:
            require_extra("x.py", "rllib", module)
        assert str(exit_info.value) == (
            f"x.py: error: needs the rllib extra ({module} is not installed): "
            "pip install -e '.[rllib]'"
        )
