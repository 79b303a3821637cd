"""Scene encoder: per-agent context ``C_i`` from histories, pair features and map crops.

RiskFlow (docs/explanation/method.md): each agent's history is embedded in the agent's own
current frame, cut into tokens of ``history_patch`` steps, and passed through
alternating *temporal* attention (over one agent's tokens) and *social* attention
(over agents, at each token) layers; social attention gets an additive bias
``b(e_ij)`` from an MLP over the pairwise features ``e_ij`` of the current step
(``riskflow_env.risk.pairwise_features``). A CNN over the agent's map crop gives
``m_i`` (``map_encoder.py``). The context is the fusion MLP

    C_i = f(h_i, m_i, mean_j MLP(e_ij))

with ``h_i`` the history embedding at the current token. The encoder does not depend
on the flow variables ``(z, t, r)``, so the MeanFlow objective runs it once, outside
its JVP (``meanflow.py``).

Input: a :class:`~policies.learned.window_types.WindowBatch` (``docs/how-to/windows.md``):
tensors with a leading batch axis ``B`` and a padded agent axis ``A``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from policies.learned.attention import TransformerBlock, edge_bias, social_mask
from policies.learned.config import HISTORY_FEATURES, ModelConfig
from policies.learned.embeddings import MLP, masked_mean
from policies.learned.map_encoder import MapEncoder
from policies.learned.packing import AgentPacking
from policies.learned.window_types import WindowBatch
from riskflow_env.geometry import to_frame

# Fields the encoder reads, with their shapes (B, A: batch and agent axes).
ENCODER_FIELDS = {
    "history": ("B", "A", "history_steps", 4),
    "history_valid": ("B", "A", "history_steps"),
    "agent_mask": ("B", "A"),
    "length": ("B", "A"),
    "width": ("B", "A"),
    "map_crops": ("B", "A", "map_channels", "map_size", "map_size"),
    "pair_features": ("B", "A", "A", 8),
    "pair_mask": ("B", "A", "A"),
}


def check_batch(batch: WindowBatch, config: ModelConfig) -> tuple[int, int]:
    """Validate the encoder's inputs; return ``(B, A)``.

    Raises:
        TypeError: ``batch`` is not a :class:`WindowBatch`.
        ValueError: naming a field whose shape is not the one ``config`` expects.
    """
    if not isinstance(batch, WindowBatch):
        raise TypeError(
            f"the encoder takes a WindowBatch (docs/how-to/windows.md), got {type(batch)}"
        )
    sizes = {"B": batch.batch_size, "A": batch.num_agents}
    for name, spec in ENCODER_FIELDS.items():
        expected = tuple(
            sizes[d] if d in sizes else getattr(config, d) if isinstance(d, str) else d
            for d in spec
        )
        shape = tuple(getattr(batch, name).shape)
        if shape != expected:
            raise ValueError(f"batch.{name} must have shape {spec} = {expected}, got {shape}")
    return sizes["B"], sizes["A"]


def history_features(batch: WindowBatch) -> Tensor:
    """Each agent's history in its own current frame.

    Args:
        batch: ``history (B, A, T, 4)`` (x, y [m], v [m/s], psi [rad]) in the scene
            frame, current step last; ``history_valid (B, A, T)``; ``length, width
            (B, A)`` [m].

    Returns:
        ``(B, A, T, 8)`` in ``config.HISTORY_FEATURES`` order: position [m] relative
        to the current pose and rotated into the current heading, cos/sin of the
        heading change, speed [m/s], validity, length and width [m]; zero where the
        step is not observed.
    """
    history, valid = batch.history, batch.history_valid
    current = history[:, :, -1:, :]  # (B, A, 1, 4)
    cos0, sin0 = torch.cos(current[..., 3]), torch.sin(current[..., 3])
    dx, dy = history[..., 0] - current[..., 0], history[..., 1] - current[..., 1]
    dpsi = history[..., 3] - current[..., 3]
    size = torch.broadcast_to(batch.length[..., None], dx.shape)
    features = torch.stack(
        [
            *to_frame(dx, dy, cos0, sin0),
            torch.cos(dpsi),
            torch.sin(dpsi),
            history[..., 2],
            valid.to(history.dtype),
            size,
            torch.broadcast_to(batch.width[..., None], dx.shape),
        ],
        dim=-1,
    )
    return features * valid[..., None].to(history.dtype)


@dataclass(frozen=True)
class SceneContext:
    """Everything the MeanFlow head needs about a batch of scenes.

    Attributes:
        context: ``(B, A, context_dim)`` per-agent context ``C_i`` (0 for padded agents).
        edges: ``(B, A, A, edge_dim)`` pair embeddings ``MLP(e_ij)`` (the head's
            social attention bias is computed from them).
        social_mask: ``(B, A, A)`` bool, see ``attention.social_mask``.
        agent_mask: ``(B, A)`` bool, agents that exist at the current step.
        state: ``(B, A, 4)`` current state (x, y [m], v [m/s], psi [rad]), scene frame:
            the initial state of every plan's rollout.
    """

    context: Tensor
    edges: Tensor
    social_mask: Tensor
    agent_mask: Tensor
    state: Tensor

    def repeat_scenes(self, num_samples: int) -> SceneContext:
        """Each scene repeated ``num_samples`` times in a row: batch ``B * num_samples``."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return SceneContext(
            **{k: v.repeat_interleave(num_samples, dim=0) for k, v in fields.items()}
        )


class SceneEncoder(nn.Module):
    """``batch -> SceneContext``: history tokens, temporal/social attention, map CNN."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        dim, patch, num_features = config.encoder_dim, config.history_patch, len(HISTORY_FEATURES)
        scale = torch.tensor(config.history_scale, dtype=torch.float32)
        pair_scale = torch.tensor(config.pair_scale, dtype=torch.float32)
        self.register_buffer("history_inv_scale", 1.0 / scale, persistent=False)
        self.register_buffer("pair_inv_scale", 1.0 / pair_scale, persistent=False)
        self.token_proj = nn.Linear(patch * num_features, dim)
        self.token_pos = nn.Parameter(0.02 * torch.randn(config.history_tokens, dim))
        self.edge_mlp = MLP(len(config.pair_scale), config.edge_dim, config.edge_dim)
        self.temporal = nn.ModuleList(
            TransformerBlock(dim, config.num_heads, config.mlp_ratio)
            for _ in range(config.encoder_layers)
        )
        self.social = nn.ModuleList(
            TransformerBlock(dim, config.num_heads, config.mlp_ratio)
            for _ in range(config.encoder_layers)
        )
        self.social_bias = nn.ModuleList(
            nn.Linear(config.edge_dim, config.num_heads) for _ in range(config.encoder_layers)
        )
        self.norm = nn.LayerNorm(dim)
        self.map_encoder = MapEncoder(config, dim)
        self.fusion = MLP(2 * dim + config.edge_dim, config.context_dim, config.context_dim)

    def _tokens(self, batch: WindowBatch, packing: AgentPacking) -> tuple[Tensor, Tensor]:
        """History tokens ``(M, N, D)`` of the packed real agents and the validity of
        every slot's tokens ``(B, A, N)``."""
        patch, tokens = self.config.history_patch, self.config.history_tokens
        pad = tokens * patch - batch.history.shape[2]  # zero steps in front of the oldest one
        valid = F.pad(batch.history_valid, (pad, 0))
        batch_size, agents = valid.shape[:2]
        features = packing.pack(history_features(batch)) * self.history_inv_scale  # (M, T, F)
        features = F.pad(features, (0, 0, pad, 0))
        x = self.token_proj(features.reshape(features.shape[0], tokens, -1)) + self.token_pos
        return x, valid.reshape(batch_size, agents, tokens, patch).any(dim=-1)

    def forward(self, batch: WindowBatch) -> SceneContext:
        """Encode a batch of windows (``docs/how-to/windows.md``; the future fields are ignored).

        Every per-agent layer runs on the real agents only (``packing.py``); the social
        attention scores of each scene use the padded agent axis.
        """
        check_batch(batch, self.config)
        agent_mask, pair_mask = batch.agent_mask.bool(), batch.pair_mask.bool()
        packing = AgentPacking.from_mask(agent_mask)
        x, token_valid = self._tokens(batch, packing)  # (M, N, D), (B, A, N)
        edges = self.edge_mlp(batch.pair_features * self.pair_inv_scale)  # (B, A, A, E)
        social = social_mask(pair_mask, agent_mask)  # (B, A, A)
        temporal_mask = packing.pack(token_valid)[:, None, :]  # (M, 1, N): observed keys
        # Social keys: other agents observed at this token; an existing agent always sees itself.
        eye = torch.eye(social.shape[-1], dtype=torch.bool, device=social.device)
        keys = token_valid.transpose(1, 2)[:, :, None, :] | eye  # (B, N, A, A)
        token_social_mask = social[:, None] & keys
        for temporal, social_block, bias_proj in zip(
            self.temporal, self.social, self.social_bias, strict=True
        ):
            x = temporal(x, temporal_mask)
            x = social_block(x, token_social_mask, edge_bias(edges, bias_proj), packing)
        history = self.norm(x[:, -1])  # (M, D): the token holding the current step
        map_embedding = self.map_encoder.embed(packing.pack(batch.map_crops))  # (M, D)
        pooled_edges = packing.pack(masked_mean(edges, pair_mask, dim=2))  # (M, E)
        context = self.fusion(torch.cat([history, map_embedding, pooled_edges], dim=-1))
        return SceneContext(
            context=packing.unpack(context),  # 0 for padded agents
            edges=edges,
            social_mask=social,
            agent_mask=agent_mask,
            state=batch.history[:, :, -1],
        )
