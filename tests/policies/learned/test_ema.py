"""EMA of the weights: the update rule and its state round trip."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from policies.learned.ema import EMA


def test_update_is_the_moving_average():
    model = nn.Linear(3, 2)
    start = [p.detach().clone() for p in model.parameters()]
    ema = EMA(model, decay=0.9)
    assert not any(p.requires_grad for p in ema.model.parameters())
    with torch.no_grad():
        for param in model.parameters():
            param.add_(1.0)
    ema.update(model)
    ema.update(model)
    for averaged, initial in zip(ema.model.parameters(), start, strict=True):
        # two steps towards (initial + 1): 1 - 0.9^2 of the way
        torch.testing.assert_close(averaged, initial + (1 - 0.9**2))


def test_state_round_trip_and_checks():
    model = nn.Linear(3, 2)
    ema = EMA(model, decay=0.5)
    with torch.no_grad():
        model.weight.mul_(2.0)
    ema.update(model)
    restored = EMA(nn.Linear(3, 2), decay=0.5)
    restored.load_state_dict(ema.state_dict())
    for a, b in zip(ema.model.parameters(), restored.model.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    with pytest.raises(ValueError, match="decay"):
        EMA(model, decay=1.0)
