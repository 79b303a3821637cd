"""Where the tests find the ScenarioNet nuScenes samples (not shipped with the repo)."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENARIONET_DIR = Path(
    os.environ.get("RISKFLOW_SCENARIONET_DIR", ROOT / "../shared/data/scenarionet")
).resolve()
