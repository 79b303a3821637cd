"""Exponential moving average of a model's weights (the weights that are evaluated and shipped).

After every optimiser step ``theta_ema <- decay * theta_ema + (1 - decay) * theta``;
with ``decay = 0.995`` (docs/explanation/method.md) the average spans about
``1 / (1 - decay) = 200`` steps. Buffers are copied, not averaged.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn


class EMA:
    """A frozen copy of ``model`` that tracks the moving average of its parameters.

    Args:
        model: the trained model; its current weights start the average.
        decay: weight of the old average per update, in [0, 1).

    Attributes:
        model: the averaged copy (``eval()`` mode, no gradients); evaluate this one.
        decay: see above.
    """

    def __init__(self, model: nn.Module, decay: float = 0.995) -> None:
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"EMA decay must be in [0, 1), got {decay}")
        self.decay = float(decay)
        self.model = copy.deepcopy(model).eval().requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the average towards ``model``'s current weights (same architecture)."""
        weight = 1.0 - self.decay
        for mine, theirs in zip(self.model.parameters(), model.parameters(), strict=True):
            mine.lerp_(theirs.detach(), weight)
        for mine, theirs in zip(self.model.buffers(), model.buffers(), strict=True):
            mine.copy_(theirs)

    def state_dict(self) -> dict[str, Any]:
        """``{"decay", "state_dict"}`` (tensors on the CPU) for a training checkpoint."""
        state = {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()}
        return {"decay": self.decay, "state_dict": state}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output (the decay is kept from the constructor)."""
        weights: Mapping[str, Tensor] = state["state_dict"]
        loader = getattr(self.model, "load_checkpoint_state", self.model.load_state_dict)
        loader(weights)
