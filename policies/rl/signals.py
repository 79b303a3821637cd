"""A clean stop on Ctrl-C / SIGTERM for the training scripts (no dependency).

``with StopSignals() as stop:`` turns SIGINT and SIGTERM into a flag the training loop
polls (``stop.received``), so that it can save a checkpoint and exit with one line instead
of a traceback; :func:`ignore_interrupts_in_worker` keeps worker processes, which a
terminal's Ctrl-C or a job's SIGTERM reaches too, alive until the main process closes them.
"""

from __future__ import annotations

import signal
import sys
from typing import Any, NoReturn


class StopSignals:
    """Within ``with StopSignals() as stop:``, SIGINT (Ctrl-C) and SIGTERM set
    ``stop.received`` (the signal's number) instead of raising or killing: the training
    loop polls it and stops at the next step. A second signal raises ``KeyboardInterrupt``
    (the user insists). The previous handlers come back on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, frame: Any) -> None:
        if self.received is not None:
            raise KeyboardInterrupt
        self.received = signum

    def __enter__(self) -> StopSignals:
        for signum in self.SIGNALS:
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: Any) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def exit_stopped(signum: int, message: str) -> NoReturn:
    """Print ``message`` with ``{name}`` replaced by the signal's name (``SIGINT``) on
    stderr and exit with the shell's status for that signal, ``128 + signum`` (130 for
    Ctrl-C, 143 for SIGTERM)."""
    print(message.format(name=signal.Signals(signum).name), file=sys.stderr)
    sys.exit(128 + signum)


def ignore_interrupts_in_worker() -> None:
    """In a worker process (SubprocVecEnv, shards), ignore SIGINT and SIGTERM: Ctrl-C
    reaches every process of the terminal's group, and a scheduler's SIGTERM
    (``kill -- -PGID``, Slurm's ``scancel``) every process of the job; the main process
    stops the workers itself after saving (a worker whose parent is gone ends on its
    closed pipe). Does nothing in the main process."""
    import multiprocessing

    if multiprocessing.parent_process() is not None:
        for signum in StopSignals.SIGNALS:
            signal.signal(signum, signal.SIG_IGN)
