"""Shared test setup: headless rendering, one thread per pytest-xdist worker, and the tiers.

Tiers (markers registered in pyproject.toml). Every test gets exactly one of ``unit``,
``integration``, ``docs`` and ``reliability``, given here by path, fixture and name so that
no test file has to list its own:

1. a tier marker the test's file gives it (``pytestmark`` or a decorator) is kept: the
   reliability tests (docs/reference/reliability.md) are marked where they are written;
2. ``docs``: tests/test_docs.py (every README / docs snippet, run in a subprocess);
3. ``integration``: tests that build envs and policies and run closed loops, or run the
   programs as a user does: every test under ``INTEGRATION_PATHS``, every test that uses a
   fixture of ``INTEGRATION_FIXTURES`` and every test whose function name matches
   ``INTEGRATION_NAMES``;
4. ``unit``: every other test.

``slow`` comes on top of the tier: tests marked so in their file, and those of ``SLOW``
(tests that cannot be made shorter without asserting less). ``pyproject.toml`` runs
``-m 'not docs and not reliability and not slow'`` by default; a ``-m`` on the command line
replaces it (``-m docs``, ``-m reliability``, ``-m slow``, ``-m unit``; ``-m ''`` runs all).
tests/test_tiers.py checks that every path named here exists and that every test has one tier.
``.ci/run`` runs every tier.
"""

from __future__ import annotations

import os
import re

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")
if os.environ.get("PYTEST_XDIST_WORKER"):
    # pytest-xdist runs one worker per core: one thread each (and in the processes the tests
    # start), not every worker's torch and BLAS spreading over every core.
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(variable, "1")

TIERS = ("unit", "integration", "docs", "reliability")
DOCS = "tests/test_docs.py"
# Path prefixes (relative to the repository) of tests that run the programs or closed loops.
INTEGRATION_PATHS = (
    "tests/examples/",  # the example scripts, run as a user runs them
    "tests/benchmarks/",  # the benchmark scripts at tiny sizes
    "tests/policies/test_evaluation",  # riskflow-eval: closed-loop rollouts of methods
    "tests/policies/test_rl",  # PPO / multi-agent training against the adversary
    "tests/policies/test_harness.py",  # the closed-loop harness
    "tests/policies/test_leaving_vehicles.py",  # evaluation rollouts, per scene and batched
    "tests/policies/pipeline/test_batched.py",  # batched vs per-scene closed loops
    "tests/policies/pipeline/test_default_rollouts.py",  # the shipped methods' rollouts
    "tests/riskflow_env/scenarios/test_cli.py",  # riskflow-data generate, worker processes
)
INTEGRATION_FIXTURES = frozenset({"closed_loop", "local_ray"})
INTEGRATION_NAMES = re.compile(r"closed_loop|end_to_end|subprocess")
# Node-id prefix -> why it is slow; for tests whose files do not mark them themselves.
SLOW: dict[str, str] = {}


def tier(item: pytest.Item, path: str) -> str:
    """The tier of ``item`` (``path``: its file relative to the repository), by the rules of
    this module's docstring."""
    given = [name for name in TIERS if item.get_closest_marker(name)]
    if len(given) > 1:
        raise pytest.UsageError(f"{item.nodeid} is marked {given}: one tier per test")
    if given:
        return given[0]
    if path == DOCS:
        return "docs"
    if (
        path.startswith(INTEGRATION_PATHS)
        or INTEGRATION_FIXTURES.intersection(getattr(item, "fixturenames", ()))
        or INTEGRATION_NAMES.search(getattr(item, "originalname", item.name))
    ):
        return "integration"
    return "unit"


@pytest.hookimpl(tryfirst=True)  # before -m deselects by these markers
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        path = item.path.relative_to(config.rootpath).as_posix()
        item.add_marker(tier(item, path))
        if any(item.nodeid.startswith(prefix) for prefix in SLOW):
            item.add_marker(pytest.mark.slow)
    # The integration tests first (a stable sort: files keep their order): pytest-xdist hands
    # tests out in this order, so the long ones start early and do not end the run alone.
    items.sort(key=lambda item: item.get_closest_marker("integration") is None)


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance with 2 CPUs for the tests of one module (the rllib or ray extra;
    skipped, with the reason, without it); shut down after them."""
    ray = pytest.importorskip(
        "ray", reason="ray is not installed (pip install -e '.[rllib]'; .ci/run installs it)"
    )
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()
