"""Small building blocks: sinusoidal time embeddings, MLPs and masked pooling.

Every op here has a forward-mode AD rule, so the blocks can sit inside the
``torch.func.jvp`` of the MeanFlow objective (``meanflow.py``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def sinusoidal_embedding(x: Tensor, num_frequencies: int, max_period: float = 10_000.0) -> Tensor:
    """Transformer-style sinusoidal features of a scalar, differentiable in ``x``.

    Args:
        x: ``(...)`` positions (here ``time_scale * t`` or ``time_scale * (r - t)``).
        num_frequencies: number of frequencies ``k``; geometric from 1 to ``1 / max_period``.
        max_period: longest period.

    Returns:
        ``(..., 2 k)`` ``[cos(x w_0), ..., cos(x w_{k-1}), sin(x w_0), ...]``.
    """
    exponent = torch.arange(num_frequencies, device=x.device, dtype=x.dtype) / num_frequencies
    freqs = torch.exp(-math.log(max_period) * exponent)
    angles = x[..., None] * freqs
    return torch.cat([torch.cos(angles), torch.sin(angles)], dim=-1)


class MLP(nn.Sequential):
    """``Linear -> GELU -> Linear`` (optionally more hidden layers, all the same width)."""

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, num_hidden: int = 1) -> None:
        layers: list[nn.Module] = []
        width = in_dim
        for _ in range(num_hidden):
            layers += [nn.Linear(width, hidden_dim), nn.GELU()]
            width = hidden_dim
        layers.append(nn.Linear(width, out_dim))
        super().__init__(*layers)


class TimeEmbedding(nn.Module):
    """Embedding of the MeanFlow time pair ``(t, r)`` (Geng et al. 2025, section 4.3).

    As in MeanFlow, the network is conditioned on ``t`` and the interval ``r - t``
    (rather than ``r``): each gets a sinusoidal embedding and an MLP, and the two are
    summed. Differentiable in ``t`` and ``r`` (the JVP tangent ``dt = 1`` flows here).
    """

    def __init__(self, num_frequencies: int, out_dim: int, time_scale: float) -> None:
        super().__init__()
        self.num_frequencies = num_frequencies
        self.time_scale = time_scale
        self.t_mlp = MLP(2 * num_frequencies, out_dim, out_dim)
        self.interval_mlp = MLP(2 * num_frequencies, out_dim, out_dim)

    def forward(self, t: Tensor, r: Tensor) -> Tensor:
        """Args: ``t, r``: ``(...)`` times in [0, 1], ``r >= t``. Returns ``(..., out_dim)``."""
        emb_t = sinusoidal_embedding(self.time_scale * t, self.num_frequencies)
        emb_interval = sinusoidal_embedding(self.time_scale * (r - t), self.num_frequencies)
        return self.t_mlp(emb_t) + self.interval_mlp(emb_interval)


def masked_mean(x: Tensor, mask: Tensor, dim: int) -> Tensor:
    """Mean of ``x`` over ``dim`` where ``mask``; 0 where nothing is valid.

    Args:
        x: ``(..., N, ..., D)`` values.
        mask: bool, ``x``'s shape without the last dim.
        dim: axis of ``mask`` (and of ``x``) to reduce; must not be the feature axis.
    """
    weight = mask.to(x.dtype)[..., None]
    total = (x * weight).sum(dim=dim)
    count = weight.sum(dim=dim).clamp(min=1.0)
    return total / count
