"""Worker processes that die with their parent.

A pool worker blocks on its task queue; when the parent is killed (``kill -9``, OOM) no one
closes that queue, so an orphaned worker finishes its queued tasks, keeps writing files,
then waits forever. :func:`exit_with_parent`, given as a pool's ``initializer``, starts a
daemon thread that ends the worker (``os._exit``) as soon as the parent is gone:

* under ``multiprocessing`` it waits on the parent's sentinel
  (``multiprocessing.parent_process().sentinel``: a pipe end on POSIX, the parent's
  process handle on Windows), which becomes ready exactly when the parent exits;
* otherwise it polls ``os.getppid()`` every ``poll_s`` seconds (orphans are adopted by
  another process on POSIX).

Both are portable; no ``prctl(PR_SET_PDEATHSIG)`` (Linux only).

:func:`pool_worker`, the initializer of the library's worker pools, also leaves Ctrl-C to
the parent: a terminal sends SIGINT to every process of the foreground group, and workers
that raised ``KeyboardInterrupt`` each printed a traceback while the parent, which keeps
what is finished and ends the pool (``Pool.terminate``), printed one line.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time

PARENT_GONE_EXIT = 70  # exit status of a worker whose parent died
MAX_WORKERS = 256  # [-] largest --workers of a command (processes or Ray CPUs)
MAX_THREADS = 256  # [-] largest torch CPU thread count a command or policy accepts


def _watch(sentinel: int | None, parent_pid: int, poll_s: float) -> None:
    if sentinel is not None:
        multiprocessing.connection.wait([sentinel])
    else:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
    os._exit(PARENT_GONE_EXIT)  # no cleanup: the parent owns the outputs


def exit_with_parent(poll_s: float = 1.0) -> None:
    """End this process as soon as its parent process ends (call it in the child).

    Args:
        poll_s: [s] polling period when no parent sentinel is available.
    """
    parent = multiprocessing.parent_process()
    sentinel = None if parent is None else parent.sentinel
    watcher = threading.Thread(
        target=_watch,
        args=(sentinel, os.getppid(), poll_s),
        name="exit-with-parent",
        daemon=True,
    )
    watcher.start()


def pool_worker() -> None:
    """A pool's ``initializer``: :func:`exit_with_parent`, and SIGINT ignored (module
    docstring)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    exit_with_parent()
