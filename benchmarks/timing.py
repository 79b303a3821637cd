"""Interleaved wall-clock timing of the benchmark scripts (a helper, not a benchmark).

The functions of one measurement run in turn within each repetition, so a peer measured
in the same run sees the same machine load. A script of this folder imports it as
``from timing import interleaved_ms``: the folder of ``python benchmarks/<name>.py`` is
on ``sys.path``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from tqdm import tqdm

from riskflow_env.compiled import SWITCH


def _no_sync() -> None:
    """CPU work is done when the call returns."""


def interleaved_ms(
    fns: dict[str, Callable[[], object]],
    repeats: int,
    warmup: int,
    sync: Callable[[], object] = _no_sync,
) -> dict[str, list[float]]:
    """Wall times [ms] of ``repeats`` calls of each function, after ``warmup`` untimed
    rounds; ``sync`` runs after every call and is timed with it (e.g.
    ``torch.cuda.synchronize``). Shows a progress bar on stderr."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    sync()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in tqdm(range(repeats), "timed repetitions", leave=False):  # stderr
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            sync()
            times[name].append(1e3 * (time.perf_counter() - start))
    return times


@contextmanager
def step_path(path: str) -> Iterator[None]:
    """Run the code inside on ``path``: 'compiled' (the numba kernels of the simulator step
    and of the planning loops, where numba is installed) or 'reference' (the array-API
    functions: ``RISKFLOW_COMPILED=0``)."""
    before = os.environ.get(SWITCH)
    os.environ[SWITCH] = "1" if path == "compiled" else "0"
    try:
        yield
    finally:
        if before is None:
            del os.environ[SWITCH]
        else:
            os.environ[SWITCH] = before


def startup_runs(script: str) -> dict[str, float]:
    """One-off costs [s] of compiled code, each in a fresh Python process running
    ``script``, which prints two numbers last: the import [s] and the first call's cost
    [s]. Two processes share one empty numba cache directory: the first compiles, the
    second loads what the first wrote. Returns ``import`` (the second's), ``compile`` and
    ``load`` (the first call's cost in each)."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, SWITCH: "1"}
        runs = []
        for _ in range(2):  # cold, then cached
            out = subprocess.run(
                [sys.executable, "-c", script], env=env, capture_output=True, text=True
            )
            if out.returncode:
                raise RuntimeError(f"start-up measurement failed:\n{out.stderr[-2000:]}")
            runs.append([float(value) for value in out.stdout.split()[-2:]])
    return {"import": runs[1][0], "compile": runs[0][1], "load": runs[1][1]}
