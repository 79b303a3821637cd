"""Where the tests find the ScenarioNet nuScenes samples (not shipped with the repo)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENARIONET_DIR = Path(
    os.environ.get("RISKFLOW_SCENARIONET_DIR", ROOT / "../shared/data/scenarionet")
).resolve()
SAMPLES = sorted(SCENARIONET_DIR.glob("*.pkl")) if SCENARIONET_DIR.is_dir() else []
MISSING = (
    f"no ScenarioNet sample pickles (*.pkl) in {SCENARIONET_DIR}: the nuScenes samples are"
    " not shipped; set RISKFLOW_SCENARIONET_DIR to their folder (README, Real data)."
    " The loader is still covered by the synthetic-description tests"
    " (test_scenarionet_sources.py)"
)


def require_samples() -> list[Path]:
    """The sample files; skip without them, fail under CI (``CI`` set), where they must be
    present."""
    if SAMPLES:
        return SAMPLES
    if os.environ.get("CI"):
        pytest.fail(f"{MISSING}. CI is set: the samples are required there", pytrace=False)
    pytest.skip(MISSING)


COMMONROAD_DIR = Path(
    os.environ.get("RISKFLOW_COMMONROAD_DIR", ROOT / "../shared/data/commonroad")
).resolve()
COMMONROAD = sorted(COMMONROAD_DIR.glob("*.xml")) if COMMONROAD_DIR.is_dir() else []
COMMONROAD_MISSING = (
    f"no CommonRoad scenarios (*.xml) in {COMMONROAD_DIR}: the NGSIM samples are not shipped;"
    " set RISKFLOW_COMMONROAD_DIR to their folder"
)


def require_commonroad() -> list[Path]:
    """The CommonRoad sample files; skip without them, fail under CI (``CI`` set)."""
    if COMMONROAD:
        return COMMONROAD
    if os.environ.get("CI"):
        pytest.fail(f"{COMMONROAD_MISSING}. CI is set: they are required there", pytrace=False)
    pytest.skip(COMMONROAD_MISSING)
