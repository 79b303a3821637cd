"""exit_with_parent: a worker ends as soon as its parent is killed (issue 19 item 5)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc"),
    pytest.mark.reliability,  # docs/reference/reliability.md
]

# the parent starts one child, prints its pid, then waits to be killed
POOL_PARENT = """
import multiprocessing, time
from riskflow_env.processes import exit_with_parent
if __name__ == "__main__":
    with multiprocessing.get_context("spawn").Pool(1, initializer=exit_with_parent) as pool:
        print(pool.apply(__import__("os").getpid), flush=True)
        pool.apply_async(time.sleep, (120,))
        time.sleep(120)
"""
PLAIN_PARENT = """
import subprocess, sys, time
code = "from riskflow_env.processes import exit_with_parent; import time; "
code += "exit_with_parent(poll_s=0.05); print('ready', flush=True); time.sleep(120)"
child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
assert child.stdout.readline().strip() == "ready"
print(child.pid, flush=True)
time.sleep(120)
"""


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("parent_code", [POOL_PARENT, PLAIN_PARENT], ids=["pool", "getppid"])
def test_child_ends_when_its_parent_is_killed(tmp_path, parent_code):
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(parent_code))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    parent = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        child = int(parent.stdout.readline())
        assert _alive(child)
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()
    deadline = time.monotonic() + 15
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    if _alive(child):
        os.kill(child, signal.SIGKILL)
        pytest.fail("the child outlived its killed parent")
