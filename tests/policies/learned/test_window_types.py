"""Window and WindowBatch: field checks, collation, device moves, scene slices."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from policies.learned.synthetic import synthetic_batch
from policies.learned.window_types import (
    FUTURE_FIELDS,
    PAD_INDEX,
    WINDOW_FIELDS,
    Window,
    WindowBatch,
    collate_windows,
)


def make_window(num_agents: int, with_future: bool = True, seed: int = 0) -> Window:
    """A window of random values with the shapes of docs/how-to/windows.md (H=3, F=4, S=5)."""
    rng = np.random.default_rng(seed)
    a = num_agents
    future = {}
    if with_future:
        future = {
            "future": rng.normal(size=(a, 4, 4)).astype(np.float32),
            "future_valid": rng.random((a, 4)) < 0.8,
            "actions": rng.normal(size=(a, 4, 2)).astype(np.float32),
            "actions_valid": rng.random((a, 4)) < 0.8,
        }
    return Window(
        history=rng.normal(size=(a, 3, 4)).astype(np.float32),
        history_valid=rng.random((a, 3)) < 0.8,
        agent_mask=np.ones(a, dtype=bool),
        agent_index=np.arange(a, dtype=np.int64) + 10,
        length=rng.uniform(4, 5, a).astype(np.float32),
        width=rng.uniform(1.8, 2, a).astype(np.float32),
        map_crops=rng.normal(size=(a, 2, 5, 5)).astype(np.float32),
        pair_features=rng.normal(size=(a, a, 8)).astype(np.float32),
        pair_mask=rng.random((a, a)) < 0.5,
        **future,
    )


def test_window_checks_its_fields():
    window = make_window(3)
    assert window.num_agents == 3 and window.has_future
    assert [name for name, _ in window.arrays()] == list(WINDOW_FIELDS)
    with pytest.raises(dataclasses.FrozenInstanceError):
        window.history = window.history  # type: ignore[misc]
    with pytest.raises(ValueError, match="length"):
        dataclasses.replace(window, length=window.length[:2])
    with pytest.raises(ValueError, match="pair_mask"):
        dataclasses.replace(window, pair_mask=window.pair_mask[:, :2])
    with pytest.raises(ValueError, match="all of"):
        dataclasses.replace(window, future=None)
    live = dataclasses.replace(window, **dict.fromkeys(FUTURE_FIELDS))
    assert not live.has_future
    assert [name for name, _ in live.arrays()] == [
        name for name in WINDOW_FIELDS if name not in FUTURE_FIELDS
    ]


def test_collate_pads_every_field_and_keeps_the_values():
    windows = [make_window(2, seed=1), make_window(4, seed=2)]
    batch = collate_windows(windows)
    assert isinstance(batch, WindowBatch) and batch.has_future
    assert (batch.batch_size, batch.num_agents) == (2, 4)
    assert batch.pair_features.shape == (2, 4, 4, 8) and batch.map_crops.shape == (2, 4, 2, 5, 5)
    np.testing.assert_array_equal(batch.agent_index[0].numpy(), [10, 11, PAD_INDEX, PAD_INDEX])
    for row, window in enumerate(windows):
        a = window.num_agents
        for name, value in window.arrays():
            got = getattr(batch, name)[row]
            got = got[:a, :a] if name.startswith("pair") else got[:a]
            assert torch.equal(got, torch.from_numpy(value)), name
    assert not batch.agent_mask[0, 2:].any() and not batch.pair_mask[0, 2:].any()
    assert not batch.pair_mask[0, :, 2:].any() and not batch.future_valid[0, 2:].any()
    live = [dataclasses.replace(w, **dict.fromkeys(FUTURE_FIELDS)) for w in windows]
    assert not collate_windows(live).has_future
    with pytest.raises(ValueError, match="future fields"):
        collate_windows([windows[0], live[1]])
    with pytest.raises(TypeError, match="Window"):
        collate_windows([dict(windows[0].arrays())])
    with pytest.raises(ValueError, match="at least one"):
        collate_windows([])


def test_batch_moves_and_slices_scenes():
    batch = synthetic_batch(3, 4, seed=0)
    assert batch.agent_index.dtype == torch.int64
    padded = ~batch.agent_mask
    assert padded.any() and bool((batch.agent_index[padded] == PAD_INDEX).all())
    moved = batch.to("cpu")
    assert isinstance(moved, WindowBatch)
    for name, value in batch.tensors():
        assert getattr(moved, name) is value, name  # already there: no copy
    copied = batch.map(lambda t: t.clone())
    assert all(torch.equal(getattr(copied, n), v) for n, v in batch.tensors())
    one = batch.scenes(1, 2, 2)
    assert (one.batch_size, one.num_agents) == (1, 2)
    assert one.pair_mask.shape == (1, 2, 2) and one.actions.shape == (1, 2, 52, 2)
    assert torch.equal(one.history, batch.history[1:2, :2])
    with pytest.raises(ValueError, match="future fields"):
        dataclasses.replace(batch, **dict.fromkeys(FUTURE_FIELDS)).require_future("a loss")
    batch.require_future("a loss")
