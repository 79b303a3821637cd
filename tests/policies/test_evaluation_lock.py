"""riskflow-eval: one writer per results folder, duplicate rows counted once (issue 19)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from dataclasses import replace

import pytest

from policies.evaluation import EvalOptions, ResultsLocked, ResultsStore, prepare
from policies.evaluation.cli import main

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

TINY = EvalOptions(methods=("idm",), scenes=1, duration=1.0, report=False)

HOLD = """
import sys, time
from policies.evaluation import ResultsStore
store = ResultsStore(sys.argv[1])
store.lock()
print("locked", flush=True)
time.sleep(600)
"""


@pytest.fixture
def other_writer(tmp_path):
    """A process holding the writer lock of ``tmp_path / "out"``, killed -9 at the end."""
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True, env=env
    )
    assert holder.stdout.readline().strip() == "locked"
    yield out, holder
    if holder.poll() is None:
        holder.kill()
    holder.wait()


def test_second_writer_is_refused_naming_the_first(other_writer):
    out, holder = other_writer
    with pytest.raises(ResultsLocked, match=f"pid {holder.pid}"):
        prepare(replace(TINY, out=str(out)))
    assert not (out / "config.json").exists()  # refused before writing anything


def test_second_riskflow_eval_gets_a_usage_error(other_writer, capsys):
    out, holder = other_writer
    with pytest.raises(SystemExit) as exit_:
        main(["--methods", "idm", "--scenes", "1", "--duration", "1", "--out", str(out)])
    assert exit_.value.code == 2
    assert f"being written by another run (pid {holder.pid}" in capsys.readouterr().err


def test_lock_of_a_killed_writer_is_released(other_writer):
    out, holder = other_writer
    with pytest.raises(ResultsLocked):
        ResultsStore(out).lock()
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    store = ResultsStore(out)
    store.lock()  # the OS dropped the dead writer's lock: a resume is not blocked
    assert (out / "writer.lock").read_text().strip() == str(os.getpid())
    store.unlock()


def test_lock_in_one_process_and_release(tmp_path):
    first, second = ResultsStore(tmp_path), ResultsStore(tmp_path)
    first.lock()
    with pytest.raises(ResultsLocked):
        second.lock()
    first.unlock()
    second.lock()
    second.unlock()


def test_duplicate_rows_are_counted_once(tmp_path):
    """Two runs into one --out wrote 12 rows for 6 keys and the report counted 12."""
    rows = [{"key": f"k{i}", "value": i} for i in range(6)]
    lines = [json.dumps(row) for row in rows + rows]
    (tmp_path / "results.jsonl").write_text("\n".join(lines) + "\n")
    with pytest.warns(UserWarning, match="6 duplicate row"):
        read = ResultsStore(tmp_path).rows()
    assert read == rows  # what the report (report.py) and resume (done_keys) read
