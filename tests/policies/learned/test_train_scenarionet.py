"""riskflow-train --data on a ScenarioNet dataset folder: windows cut one scene at a time,
cached beside the data, errors naming --data."""

from __future__ import annotations

import json

import numpy as np

from policies.learned.data import WindowDataset
from policies.train import GENERATOR
from policies.train import main as train_main
from riskflow_env.scenarios.map_cache import MapCache
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset


def _args(data, out, config, *extra: str) -> list[str]:
    return [
        "--data", str(data), "--out", str(out), "--val-fraction", "0.25",
        "--model", json.dumps(config.to_dict()), "--stride", "16", "--batch-size", "2",
        "--steps", "1", "--eval-every", "1", "--val-windows", "2", "--num-samples", "2",
        *extra,
    ]  # fmt: skip


def test_windows_of_a_dataset_match_the_loaded_scenes(scenarionet_toy, tmp_path):
    dataset = ScenarioNetDataset(scenarionet_toy, map_cache=MapCache(tmp_path / "maps"))
    lazy = WindowDataset(dataset, stride=16)
    eager = WindowDataset([dataset.load(i) for i in range(len(dataset))], stride=16)
    assert len(lazy) == len(eager) > 0
    np.testing.assert_array_equal(lazy.index, eager.index)
    for item in range(len(lazy)):
        for key, value in lazy.window(item).arrays():
            np.testing.assert_array_equal(value, getattr(eager.window(item), key), err_msg=key)


def test_train_on_a_dataset_folder_then_from_the_window_cache(
    scenarionet_toy, tmp_path, tiny_config, monkeypatch
):
    assert train_main(_args(scenarionet_toy, tmp_path / "run", tiny_config)) == 0
    assert (tmp_path / "run" / GENERATOR).is_file()
    cached = {path.name for path in (scenarionet_toy / "cache").iterdir()}
    assert {"windows-stride16-val0.25-train.npz", "windows-stride16-val0.25-val.npz"} <= cached
    assert (scenarionet_toy / "norm_stats.json").is_file()

    def refuse(self, index):
        raise AssertionError("a scene was read although its windows are cached")

    monkeypatch.setattr(ScenarioNetDataset, "load", refuse)
    assert train_main(_args(scenarionet_toy, tmp_path / "again", tiny_config)) == 0


def test_bad_dataset_folder_names_the_argument(scenarionet_toy, tmp_path, tiny_config, refused):
    next(scenarionet_toy.glob("*/*toy-2.pkl")).unlink()
    with refused(r"riskflow-train: error: --data: .*1 scenario file\(s\) listed"):
        train_main(_args(scenarionet_toy, tmp_path / "run", tiny_config))
    (scenarionet_toy / "dataset_summary.pkl").write_bytes(b"\x80\x04N.")
    with refused(r"--data: .*dataset_summary.pkl: expected a dict"):
        train_main(_args(scenarionet_toy, tmp_path / "run", tiny_config))
