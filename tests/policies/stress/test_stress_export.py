"""``riskflow-stress --export``: every saved failure's executed episode is written beside
its replay file in the formats asked for; a bad format is a usage error naming --export."""

from __future__ import annotations

import numpy as np
import pytest

from policies.stress import load_replay
from policies.stress.cli import main
from riskflow_env.scenarios import save_scenario, shipped_bank
from riskflow_env.scenarios.scenarionet import load_scenarionet
from tests.policies.stress.planner_sources import RECKLESS
from tests.riskflow_env.scenarios.interop import import_error

pytestmark = pytest.mark.integration

# the interop formats when their libraries import (commonroad-io fails with a newer protobuf
# imported first); ScenarioNet alone otherwise
INTEROP = import_error("scenariogeneration", "commonroad.common.file_reader") is None


def test_every_failure_is_exported_beside_its_replay(tmp_path, capsys):
    planner = tmp_path / "user.py"
    planner.write_text(RECKLESS)
    scenes = tmp_path / "scenes"
    save_scenario(shipped_bank("eval")[7], scenes / "busy.npz")
    formats = "scenarionet,openscenario,commonroad" if INTEROP else "scenarionet"
    out = tmp_path / "run"
    main([
        "--planner", f"{planner}:reckless", "--data", str(scenes), "--scenes", "1",
        "--steps", "30", "--no-progress", "--export", formats, "--out", str(out),
    ])  # fmt: skip
    (replay_file,) = sorted((out / "failures").glob("*.npz"))
    suffixes = {".pkl", ".xosc", ".xodr", ".xml"} if INTEROP else {".pkl"}
    beside = {p.suffix for p in replay_file.parent.iterdir() if p.stem == replay_file.stem}
    assert beside == suffixes | {".npz"}
    assert "exported" in capsys.readouterr().out
    saved = load_replay(replay_file)
    back = load_scenarionet(replay_file.with_suffix(".pkl"), min_future_steps=0, crop=False)
    ego = back.states[0, back.current_index : back.current_index + saved.states.shape[1]]
    np.testing.assert_allclose(ego[:, :2], saved.states[0, :, :2], atol=1e-3)


def test_an_unknown_format_names_export(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--export", "scenarionet,sumo", "--scenes", "1", "--out", str(tmp_path)])
    assert "--export: format must be one of" in capsys.readouterr().err
