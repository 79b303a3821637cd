"""Map encoder: a small CNN over each agent's rotated, agent-centred map crop.

Gives the map embedding ``m_i`` of the RiskFlow context ``C_i = f(h_i, m_i, e_i.)``
(docs/explanation/method.md). The crops come from ``policies.learned.windows``
(``map_crops``: drivable share and SDF [m] clipped to +-10 m, 48 x 48 px at 1 m/px).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from policies.learned.config import ModelConfig


class MapEncoder(nn.Module):
    """Stride-2 ``Conv3x3 -> GELU`` stages, global average pooling, a linear layer."""

    def __init__(self, config: ModelConfig, out_dim: int) -> None:
        super().__init__()
        self.channels = config.map_channels
        self.size = config.map_size
        scale = torch.tensor(config.map_scale, dtype=torch.float32)
        self.register_buffer("inv_scale", (1.0 / scale)[:, None, None], persistent=False)
        layers: list[nn.Module] = []
        width = config.map_channels
        for out in config.map_widths:
            layers += [nn.Conv2d(width, out, kernel_size=3, stride=2, padding=1), nn.GELU()]
            width = out
        self.convs = nn.Sequential(*layers)
        self.proj = nn.Linear(width, out_dim)

    def forward(self, crops: Tensor, agent_mask: Tensor | None = None) -> Tensor:
        """Embed map crops.

        Args:
            crops: ``(B, A, C, S, S)`` agent-centred crops (channels as in ``map_scale``).
            agent_mask: optional ``(B, A)`` bool, the agents that exist; the CNN then runs
                on their crops only (padded slots of a batch get a zero embedding, which
                nothing reads: their context is masked).

        Returns:
            ``(B, A, out_dim)`` map embeddings ``m_i``.
        """
        batch, agents = crops.shape[:2]
        if agent_mask is not None and not bool(agent_mask.all()):
            packed = self.embed(crops[agent_mask])
            out = packed.new_zeros(batch, agents, packed.shape[-1])
            return out.index_put((agent_mask,), packed)
        return self.embed(crops.reshape(batch * agents, *crops.shape[2:])).reshape(
            batch, agents, -1
        )

    def embed(self, crops: Tensor) -> Tensor:
        """``(N, C, S, S)`` crops (e.g. the packed real agents') -> ``(N, out_dim)``."""
        x = crops.reshape(crops.shape[0], self.channels, self.size, self.size) * self.inv_scale
        return self.proj(self.convs(x).mean(dim=(-2, -1)))
