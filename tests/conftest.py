"""Shared test setup: headless rendering, small configs."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")


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
