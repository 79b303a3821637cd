"""riskflow-eval killed with kill -9 mid-run, then resumed: nothing lost, nothing twice
(issue 19 deliverable 6)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from policies.evaluation import ResultsStore
from policies.evaluation.cli import main

pytestmark = pytest.mark.reliability

ARGS = ["--methods", "idm", "replay", "--scenes", "3", "--duration", "1", "--no-report"]

KILLED = """
import os, signal, sys
from policies.evaluation import results
from policies.evaluation.cli import main

real_write, written = results.write_bytes, []


def write_then_die(path, data):  # config.json, then each rollout's samples file
    real_write(path, data)
    written.append(path)
    if len(written) == 4:  # the third rollout's samples are on disk, its row is not
        with open(results.Path(sys.argv[1]) / results.RESULTS, "ab") as file:
            file.write(b'{"key": "a row torn by the kill')
        os.kill(os.getpid(), signal.SIGKILL)


results.write_bytes = write_then_die
main(["--out", sys.argv[1], *sys.argv[2:]])
"""


def _numbers(out) -> dict[str, dict]:
    rows = ResultsStore(out).rows()
    assert len(rows) == len({row["key"] for row in rows})
    volatile = ("timing", "samples")  # wall times; sample file names are checked apart
    return {row["key"]: {k: v for k, v in row.items() if k not in volatile} for row in rows}


def test_kill_9_then_resume_gives_the_uninterrupted_results(tmp_path, capsys):
    out = tmp_path / "killed"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    child = subprocess.run(
        [sys.executable, "-c", KILLED, str(out), *ARGS],
        capture_output=True,
        text=True,
        timeout=600,  # a hang guard only: the machine may be loaded
        env=env,
    )
    assert child.returncode == -signal.SIGKILL, child.stderr[-2000:]
    assert len(ResultsStore(out).rows()) == 2  # two committed rows, a torn third
    main(["--out", str(out), *ARGS])  # the resume: the same command again
    assert "4 rollouts run" in capsys.readouterr().out  # 2 of 6 were on disk
    reference = tmp_path / "reference"
    main(["--out", str(reference), *ARGS])
    assert _numbers(out) == _numbers(reference)
    store = ResultsStore(out)
    assert all((out / row["samples"]).is_file() for row in store.rows())
    assert len(list((out / "samples").glob("*.npz"))) == 6
