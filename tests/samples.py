"""Where the tests find the real-data samples (not shipped with the repo): the ScenarioNet
nuScenes pickles and the CommonRoad NGSIM scenarios."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _sample_dir(variable: str, default: str) -> Path:
    """The folder ``$variable`` names, else ``default`` beside the repository."""
    return Path(os.environ.get(variable, ROOT / "../shared/data" / default)).resolve()


def _files(folder: Path, pattern: str) -> list[Path]:
    """``folder``'s files matching ``pattern``, sorted; none when there is no folder."""
    return sorted(folder.glob(pattern)) if folder.is_dir() else []


def _require(files: list[Path], missing: str, required: str) -> list[Path]:
    """``files``; skip without them, fail under CI (``CI`` set), where they must be present."""
    if files:
        return files
    if os.environ.get("CI"):
        pytest.fail(f"{missing}. CI is set: {required}", pytrace=False)
    pytest.skip(missing)


SCENARIONET_DIR = _sample_dir("RISKFLOW_SCENARIONET_DIR", "scenarionet")
SAMPLES = _files(SCENARIONET_DIR, "*.pkl")
MISSING = (
    f"no ScenarioNet sample pickles (*.pkl) in {SCENARIONET_DIR}: the nuScenes samples are"
    " not shipped; set RISKFLOW_SCENARIONET_DIR to their folder (README, Real data)."
    " The loader is still covered by the synthetic-description tests"
    " (test_scenarionet_sources.py)"
)


def require_samples() -> list[Path]:
    """The sample files; skip without them, fail under CI (``CI`` set), where they must be
    present."""
    return _require(SAMPLES, MISSING, "the samples are required there")


COMMONROAD_DIR = _sample_dir("RISKFLOW_COMMONROAD_DIR", "commonroad")
COMMONROAD = _files(COMMONROAD_DIR, "*.xml")
COMMONROAD_MISSING = (
    f"no CommonRoad scenarios (*.xml) in {COMMONROAD_DIR}: the NGSIM samples are not shipped;"
    " set RISKFLOW_COMMONROAD_DIR to their folder"
)


def require_commonroad() -> list[Path]:
    """The CommonRoad sample files; skip without them, fail under CI (``CI`` set)."""
    return _require(COMMONROAD, COMMONROAD_MISSING, "they are required there")
