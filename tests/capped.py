"""Run one loader call in a child process under an address-space cap and a timeout.

The hostile-input tests (docs/reference/reliability.md) feed small generated files to the loaders;
each call runs in its own Python process whose address space is capped
(``resource.setrlimit(RLIMIT_AS)``), so a file that would allocate gigabytes fails that
process, not the test run, and the outcome (the exception's type and message, the seconds
the call took and the memory it added to the peak) comes back as one :class:`Outcome`.

:func:`assert_bounded` is the time and memory promise of docs/reference/reliability.md.
Its time bound is on the CPU seconds of the call, not on the wall clock, and is loose
(``MAX_CPU_S``): it separates a bounded load (well under 5 s of CPU on an idle core) from
the unbounded ones it guards against (100 to 400 s), and stays true on a loaded machine,
where another process's work stretches the wall clock, not the call's CPU time.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass

CAP_BYTES = 1536 * 2**20  # [bytes] address space of the child (torch and numpy fit in it)
TIMEOUT = 120.0  # [s] the child is killed after this (imports included)
MAX_CPU_S = 20.0  # [s] of CPU a bounded call stays under (see the module docstring)
MAX_ADDED_MB = 500.0  # [MB] of peak resident memory a bounded call adds

_CHILD = """
import contextlib, io, json, resource, sys, time
resource.setrlimit(resource.RLIMIT_AS, ({cap}, {cap}))
exec(sys.argv[1])
peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
before, start, cpu, err = peak(), time.perf_counter(), time.process_time(), io.StringIO()
outcome = {{"error": None, "message": ""}}
try:
    with contextlib.redirect_stderr(err):
        exec(sys.argv[2])
except BaseException as error:
    text = str(error)
    outcome = {{"error": type(error).__name__, "message": text[:4000], "chars": len(text)}}
outcome.update(seconds=time.perf_counter() - start, cpu_seconds=time.process_time() - cpu,
               added_mb=peak() - before, stderr=err.getvalue()[-4000:])
print("OUTCOME", json.dumps(outcome))
"""


@dataclass(frozen=True)
class Outcome:
    """What a capped call did: ``error`` is the exception's type name (None when the call
    returned), ``message`` its text (its first 4,000 characters; ``chars`` its length),
    ``seconds`` the call's duration (wall clock), ``cpu_seconds`` the CPU time it used,
    ``added_mb`` what it added to the process's peak resident memory [MB], ``stderr`` what
    it printed there."""

    error: str | None
    message: str
    seconds: float
    added_mb: float
    cpu_seconds: float = 0.0
    stderr: str = ""
    chars: int = 0


def assert_bounded(outcome: Outcome) -> None:
    """The call stayed within ``MAX_CPU_S`` of CPU and added under ``MAX_ADDED_MB``."""
    assert outcome.cpu_seconds < MAX_CPU_S and outcome.added_mb < MAX_ADDED_MB, outcome


def run_capped(
    setup: str, call: str, cap_bytes: int = CAP_BYTES, timeout: float = TIMEOUT
) -> Outcome:
    """Run ``setup`` (imports: not timed), then ``call`` (timed), both Python statements,
    in a child process with its address space capped at ``cap_bytes``."""
    result = subprocess.run(
        [sys.executable, "-c", _CHILD.format(cap=int(cap_bytes)), setup, call],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    lines = [line for line in result.stdout.splitlines() if line.startswith("OUTCOME ")]
    if not lines:
        raise AssertionError(f"the child died (exit {result.returncode}): {result.stderr[-3000:]}")
    return Outcome(**json.loads(lines[-1][len("OUTCOME ") :]))
