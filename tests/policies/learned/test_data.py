"""WindowDataset, collate_windows, ActionNormalizer and the norm_stats.json file."""

from __future__ import annotations

import dataclasses
import importlib.util
import json

import numpy as np
import pytest
import torch

from policies.learned.data import (
    STATS_FILENAME,
    ActionNormalizer,
    WindowDataset,
    compute_action_stats,
    load_or_compute_stats,
    window_indices,
)
from policies.learned.window_types import PAIR_FIELDS, Window, collate_windows
from policies.learned.windows import WindowConfig, window_from_scenario
from riskflow_env.scenarios import HighwayTrafficSource

STRIDE = 16


@pytest.fixture(scope="module")
def scenarios():
    return [HighwayTrafficSource().sample(np.random.default_rng(i)) for i in range(3)]


@pytest.fixture(scope="module")
def dataset(scenarios):
    return WindowDataset(scenarios, stride=STRIDE)


def test_windows_per_scene_and_items_match_window_from_scenario(scenarios, dataset):
    config = WindowConfig()
    candidates = np.array([30, 46, 62, 78])  # 31 history + 100 future: current in [30, 78]
    total = 0
    for scenario in scenarios:
        expected = candidates[scenario.valid[scenario.ego_index, candidates]]
        np.testing.assert_array_equal(window_indices(scenario, config, STRIDE), expected)
        total += expected.size
    assert total < 3 * candidates.size, "seed 1's ego leaves its road: steps are skipped"
    assert len(dataset) == total
    assert dataset.index.tolist()[:5] == [[0, 30], [0, 46], [0, 62], [0, 78], [1, 30]]
    for item_index in (0, 5, len(dataset) - 1):
        position, current = dataset.index[item_index]
        reference = window_from_scenario(scenarios[position], int(current), config)
        item = dataset[item_index]
        assert isinstance(item, Window) and item.has_future
        for key, value in item.arrays():
            assert isinstance(value, np.ndarray)
            np.testing.assert_array_equal(value, getattr(reference, key), err_msg=key)


def test_windows_skip_steps_where_the_ego_is_invalid(scenarios):
    scenario = scenarios[0]
    valid = scenario.valid.copy()
    valid[scenario.ego_index, 46] = False
    holed = dataclasses.replace(scenario, valid=valid)
    assert window_indices(holed, WindowConfig(), STRIDE).tolist() == [30, 62, 78]
    with pytest.raises(ValueError, match="stride"):
        WindowDataset([scenario], stride=0)
    with pytest.raises(ValueError, match="no window fits"):
        WindowDataset([scenario], WindowConfig(future_steps=200))


def test_collate_pads_agents_and_masks(dataset):
    items = [dataset[i] for i in range(len(dataset))]
    counts = [item.agent_mask.shape[0] for item in items]
    assert len(set(counts)) > 1, "the fixture should mix agent counts"
    np.testing.assert_array_equal(dataset.agent_counts(), counts)
    batch = collate_windows(items)
    size = max(counts)
    assert batch.history.shape == (len(items), size, 31, 4)
    assert batch.map_crops.shape == (len(items), size, 2, 48, 48)
    assert batch.pair_features.shape == (len(items), size, size, 8)
    assert batch.history.dtype == torch.float32 and batch.agent_mask.dtype == torch.bool
    for row, (item, count) in enumerate(zip(items, counts, strict=True)):
        for key, value in item.arrays():
            index = (row,) + (slice(0, count),) * (2 if key in PAIR_FIELDS else 1)
            assert torch.equal(getattr(batch, key)[index], torch.from_numpy(value)), key
        assert not batch.agent_mask[row, count:].any()
        assert not batch.history_valid[row, count:].any()
        assert not batch.actions_valid[row, count:].any()
        assert not batch.pair_mask[row, count:].any() and not batch.pair_mask[row, :, count:].any()
        assert torch.all(batch.agent_index[row, count:] == -1)
        assert torch.all(batch.history[row, count:] == 0)
    with pytest.raises(ValueError, match="at least one"):
        collate_windows([])


def test_dataloader_batches(dataset):
    loader = torch.utils.data.DataLoader(dataset, batch_size=4, collate_fn=collate_windows)
    batch = next(iter(loader))
    assert batch.actions.shape[:1] == (4,) and batch.actions.shape[2:] == (52, 2)


def test_cache_round_trip(tmp_path, scenarios, dataset):
    path = tmp_path / "windows.npz"
    built = WindowDataset(scenarios, stride=STRIDE, cache_path=path)
    assert path.is_file()
    stamp = path.stat().st_mtime_ns
    loaded = WindowDataset(scenarios, stride=STRIDE, cache_path=path)
    assert path.stat().st_mtime_ns == stamp  # read, not rewritten
    np.testing.assert_array_equal(loaded.index, dataset.index)
    for key, value in loaded[len(loaded) - 1].arrays():
        np.testing.assert_array_equal(value, getattr(built[len(built) - 1], key), err_msg=key)
    other = WindowDataset(scenarios, stride=STRIDE * 2, cache_path=path)  # stale: rebuilt
    assert len(other) < len(loaded)


@pytest.mark.parametrize("name", ["wcache", "windows.npz"])
def test_cache_at_any_name_and_an_unreadable_cache_is_rebuilt(name, tmp_path, scenarios, dataset):
    """The cache is the file named, with or without ``.npz`` (np.savez used to append it and
    the next run missed the cache); a torn or foreign file is rebuilt with a warning."""
    path = tmp_path / name
    WindowDataset(scenarios, stride=STRIDE, cache_path=path)
    assert [p.name for p in tmp_path.iterdir()] == [name]
    stamp = path.stat().st_mtime_ns
    WindowDataset(scenarios, stride=STRIDE, cache_path=path)
    assert path.stat().st_mtime_ns == stamp  # read, not rewritten
    for unreadable in (path.read_bytes()[:100], b"not a cache"):
        path.write_bytes(unreadable)
        with pytest.warns(UserWarning, match=f"window cache {path} cannot be read"):
            rebuilt = WindowDataset(scenarios, stride=STRIDE, cache_path=path)
        np.testing.assert_array_equal(rebuilt.index, dataset.index)
        WindowDataset(scenarios, stride=STRIDE, cache_path=path)  # rewritten whole: no warning


def test_normalizer_round_trip_numpy_and_torch(dataset):
    normalizer = compute_action_stats(dataset)
    actions = dataset.valid_actions()
    assert normalizer.count == actions.shape[0]
    np.testing.assert_allclose(normalizer.mean, actions.mean(axis=0), rtol=1e-5, atol=1e-7)
    rng = np.random.default_rng(0)
    sample = rng.normal(size=(5, 52, 2))
    z = normalizer.normalize(sample)
    np.testing.assert_allclose(normalizer.denormalize(z), sample, atol=1e-9)
    tensor = torch.tensor(sample, dtype=torch.float32, requires_grad=True)
    z_torch = normalizer.normalize(tensor)
    assert z_torch.dtype == torch.float32 and z_torch.requires_grad
    np.testing.assert_allclose(z_torch.detach().numpy(), z, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(normalizer.denormalize(z_torch).detach().numpy(), sample, atol=1e-5)
    custom = ActionNormalizer(mean=(1.0, -0.5), std=(2.0, 0.25))
    np.testing.assert_allclose(custom.normalize(np.array([3.0, 0.0])), [1.0, 2.0])
    assert ActionNormalizer.from_dict(custom.to_dict()) == custom
    with pytest.raises(ValueError, match="std"):
        ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.0))
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\)"):
        custom.normalize(np.zeros((3, 4)))


def test_stats_from_window_dicts_match_the_dataset_fast_path(dataset):
    from_items = compute_action_stats([dataset.window(i) for i in range(len(dataset))])
    fast = compute_action_stats(dataset)
    assert from_items.count == fast.count
    np.testing.assert_allclose(from_items.mean, fast.mean)
    np.testing.assert_allclose(from_items.std, fast.std)


def test_stats_file_round_trip(tmp_path, dataset):
    first = load_or_compute_stats(tmp_path, dataset)
    path = tmp_path / STATS_FILENAME
    stored = json.loads(path.read_text())
    assert set(stored) == {"mean", "std", "count"} and stored["count"] == first.count
    path.write_text(json.dumps({**stored, "mean": [0.25, 0.5]}))  # the file wins once written
    second = load_or_compute_stats(tmp_path, dataset)
    assert second.mean == (0.25, 0.5) and second.std == first.std
    assert ActionNormalizer.load(path) == second
    path.write_text('{"mean": [0.0]}')
    with pytest.raises(ValueError, match="malformed"):
        ActionNormalizer.load(path)


@pytest.mark.skipif(
    importlib.util.find_spec("riskflow_env.scenarios.io") is None,
    reason="riskflow_env.scenarios.io (list_scenarios / load_scenario) is not written yet",
)
def test_dataset_from_a_directory(tmp_path, scenarios):
    from riskflow_env.scenarios import io

    save = getattr(io, "save_scenario", None)
    if save is None:
        pytest.skip("riskflow_env.scenarios.io has no save_scenario to write test files")
    for index, scenario in enumerate(scenarios):
        save(scenario, tmp_path / f"scene_{index:03d}.npz")
    cache = tmp_path / "windows.npz"  # beside the scenes: not read as one
    from_disk = WindowDataset(tmp_path, stride=STRIDE, cache_path=cache)
    assert cache.is_file()
    assert len(WindowDataset(tmp_path, stride=STRIDE, cache_path=cache)) == len(from_disk)
    in_memory = WindowDataset(scenarios, stride=STRIDE)
    assert len(from_disk) == len(in_memory)
    for key, value in from_disk[0].arrays():
        np.testing.assert_allclose(value, getattr(in_memory[0], key), err_msg=key)
