"""riskflow-train on recorded scenes: ScenarioNet folders read with smoothed tracks, mixed
with simulated banks at stated weights (--data-weights), validated on held-out scenes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from policies.learned.batches import FolderShares, batch_order, load_splits
from policies.learned.checkpoint import load_checkpoint
from policies.learned.data import WindowDataset
from policies.train import GENERATOR, TrainOptions
from policies.train import main as train_main
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset
from tests.policies.highway_banks import write_banks


def test_shares_give_each_folder_its_weight_of_an_epoch():
    folders = np.repeat([0, 1], [10, 90])  # a small folder and a large one
    shares = FolderShares(folders, (1.0, 1.0))
    order = shares.draw(40, torch.Generator().manual_seed(0))
    assert np.bincount(folders[order], minlength=2).tolist() == [20, 20]
    assert np.bincount(order[folders[order] == 0], minlength=10).tolist() == [2] * 10  # repeats
    assert len(np.unique(order[folders[order] == 1])) == 20  # no repeat where there are enough
    np.testing.assert_array_equal(order, shares.draw(40, torch.Generator().manual_seed(0)))
    thirds = FolderShares(folders, (2.0, 1.0)).draw(100, torch.Generator().manual_seed(1))
    assert np.bincount(folders[thirds]).tolist() == [67, 33]  # largest remainder
    agents = np.arange(100) % 7 + 1
    batches = batch_order(agents, 4, 2, seed=3, epoch=0, shares=shares)
    assert batches.shape == (25, 4) and np.bincount(folders[batches.ravel()]).tolist() == [50, 50]


@pytest.mark.parametrize(
    ("weights", "data", "message"),
    [
        ((1.0,), ("a",), "--data-weights only with several --data folders"),
        ((1.0, 2.0, 3.0), ("a", "b"), r"--data-weights: one weight per --data folder \(got 3"),
        ((1.0, 0.0), ("a", "b"), r"--data-weights finite and > 0 \(got \[1.0, 0.0\]"),
    ],
    ids=["one-folder", "count", "zero"],
)
def test_bad_data_weights_name_the_option(weights, data, message):
    with pytest.raises(ValueError, match=message):
        TrainOptions(data=tuple(map(Path, data)), val_data=Path("v"), data_weights=weights)


def test_recorded_windows_are_cut_from_smoothed_tracks(scenarionet_toy, tmp_path):
    """The training split of a ScenarioNet folder: the windows of its scenes loaded with
    smooth=True (the Savitzky-Golay kinematic filtering), by scene (--val-fraction)."""
    train, val = load_splits(scenarionet_toy, None, 0.25, 16)
    dataset = ScenarioNetDataset(scenarionet_toy, smooth=True)
    order = np.random.default_rng(0).permutation(len(dataset))  # the held-out scene: order[0]
    picked = sorted(int(i) for i in order[1:])
    expected = WindowDataset([dataset.load(i) for i in picked], stride=16)
    raw = WindowDataset([ScenarioNetDataset(scenarionet_toy).load(i) for i in picked], stride=16)
    assert len(train) == len(expected) > 0 and len(val) > 0
    np.testing.assert_array_equal(train.index, expected.index)
    for item in range(len(train)):
        for key, value in train.window(item).arrays():
            np.testing.assert_array_equal(value, getattr(expected.window(item), key), err_msg=key)
    assert not np.array_equal(train.window(0).actions, raw.window(0).actions)


def test_recorded_and_simulated_folders_train_together_end_to_end(
    scenarionet_toy, tmp_path, tiny_config
):
    """A ScenarioNet folder and a simulated bank at weights 3 : 1, validated on a held-out
    simulated scene: each epoch draws 3/4 of its windows from the recorded folder."""
    bank, val = write_banks((tmp_path / "bank", tmp_path / "val"), ([0], [4]))
    out = tmp_path / "run"
    args = [
        "--data", str(scenarionet_toy), str(bank), "--data-weights", "3", "1",
        "--val-data", str(val), "--out", str(out), "--model", json.dumps(tiny_config.to_dict()),
        "--stride", "16", "--batch-size", "4", "--steps", "2", "--eval-every", "2",
        "--val-windows", "2", "--num-samples", "2",
    ]  # fmt: skip
    assert train_main(args) == 0
    stored = load_checkpoint(out / GENERATOR)
    assert stored["train_config"]["data_weights"] == [3.0, 1.0]
    assert np.isfinite(stored["metrics"]["val_ade"])
    train, _ = load_splits([scenarionet_toy, bank], val, 0.1, 16)
    shares = FolderShares.of(train, [scenarionet_toy, bank], (3.0, 1.0))
    recorded = int(np.sum(shares.folders == 0))
    assert 0 < recorded < len(train)
    order = batch_order(train.agent_counts(), 4, 32, seed=0, epoch=0, shares=shares)
    drawn = np.bincount(shares.folders[order.ravel()], minlength=2)
    assert drawn[0] == 3 * drawn[1]
