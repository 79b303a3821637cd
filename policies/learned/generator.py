"""The RiskFlow generator: MeanFlow head ``u_theta(z, t, r; C)`` and the model wrapper.

MeanFlow (Geng et al. 2025, "Mean Flows for One-step Generative Modeling") learns the
*average* velocity ``u(z_t, t, r) = 1 / (r - t) * int_t^r v(z_s, s) ds`` of the flow
from noise (t = 0) to data (t = 1), so one step ``a = eps + u_theta(eps, 0, 1; C)``
samples a plan (this project's convention, docs/explanation/method.md). RiskFlow applies it
in action space: ``z`` is a normalised (accel, yaw rate) sequence of every agent.

The head cuts each agent's plan into tokens of ``plan_patch`` steps and runs
adaLN-Zero blocks (DiT, as in MeanFlow): temporal attention over the agent's tokens,
social attention over agents at each token (with the pair-feature bias ``b(e_ij)``, so
the plans of a scene are generated jointly) and an MLP, each modulated by the agent's
context ``C_i`` plus the embedding of ``(t, r - t)``. At initialisation ``u = 0``.

Checkpoints carry the ``ModelConfig`` with the state dict
(:meth:`RiskFlowGenerator.checkpoint` / :meth:`RiskFlowGenerator.from_checkpoint`);
a checkpoint that does not fit raises :class:`CheckpointError` saying what differs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from policies.learned.attention import Attention, edge_bias
from policies.learned.config import ModelConfig
from policies.learned.embeddings import MLP, TimeEmbedding
from policies.learned.encoder import SceneContext, SceneEncoder
from policies.learned.packing import AgentPacking
from policies.learned.window_types import WindowBatch

CHECKPOINT_FORMAT = "riskflow-generator/1"


class CheckpointError(ValueError):
    """A checkpoint that is malformed or does not fit the model."""


def _modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    """``x (M, N, D)`` with per-agent ``shift, scale (M, D)``."""
    return x * (1.0 + scale[:, None]) + shift[:, None]


class HeadBlock(nn.Module):
    """adaLN-Zero block: temporal attention, social attention, MLP, each gated."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: int, edge_dim: int) -> None:
        super().__init__()
        self.norms = nn.ModuleList(nn.LayerNorm(dim, elementwise_affine=False) for _ in range(3))
        self.temporal = Attention(dim, num_heads)
        self.social = Attention(dim, num_heads)
        self.social_bias = nn.Linear(edge_dim, num_heads)
        self.mlp = MLP(dim, mlp_ratio * dim, dim)
        self.modulation = nn.Linear(dim, 9 * dim)
        nn.init.zeros_(self.modulation.weight)
        nn.init.zeros_(self.modulation.bias)

    def forward(
        self, x: Tensor, cond: Tensor, scene: SceneContext, packing: AgentPacking
    ) -> Tensor:
        """Args: ``x (M, N, D)`` plan tokens and ``cond (M, D)`` of the packed real agents
        of ``scene`` (``packing``). Returns ``(M, N, D)``."""
        mods = self.modulation(cond).chunk(9, dim=-1)
        h = _modulate(self.norms[0](x), mods[0], mods[1])
        x = x + mods[2][:, None] * self.temporal(h)
        h = _modulate(self.norms[1](x), mods[3], mods[4])
        bias = edge_bias(scene.edges, self.social_bias)
        x = x + mods[5][:, None] * self.social(h, scene.social_mask[:, None], bias, packing)
        h = _modulate(self.norms[2](x), mods[6], mods[7])
        return x + mods[8][:, None] * self.mlp(h)


class MeanFlowHead(nn.Module):
    """``u_theta(z, t, r; C)``: average velocity of every agent's plan from t to r."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        dim, patch = config.head_dim, config.plan_patch * config.action_dim
        self.in_proj = nn.Linear(patch, dim)
        self.token_pos = nn.Parameter(0.02 * torch.randn(config.plan_tokens, dim))
        self.time = TimeEmbedding(config.time_frequencies, dim, config.time_scale)
        self.cond = nn.Linear(config.context_dim, dim)
        self.blocks = nn.ModuleList(
            HeadBlock(dim, config.num_heads, config.mlp_ratio, config.edge_dim)
            for _ in range(config.head_layers)
        )
        self.norm = nn.LayerNorm(dim, elementwise_affine=False)
        self.final_modulation = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, patch)
        for layer in (self.final_modulation, self.out):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def forward(self, z: Tensor, t: Tensor, r: Tensor, scene: SceneContext) -> Tensor:
        """Average velocity ``u`` of the flow of ``z`` over ``[t, r]``.

        Args:
            z: ``(B, A, T, 2)`` normalised actions ``z_t`` on the path from noise ``eps``
                (t = 0) to data ``a*`` (t = 1).
            t: ``(B,)`` or ``(B, A)`` current time in [0, 1].
            r: like ``t``, end time ``r >= t``.
            scene: the encoder output for the same ``B`` scenes.

        Returns:
            ``(B, A, T, 2)`` ``u``, so that ``z_r ~ z_t + (r - t) u``; 0 for padded agents.
        """
        batch, agents, steps, channels = z.shape
        packing = AgentPacking.from_mask(scene.agent_mask)  # every per-agent layer: real ones
        z = packing.pack(z)  # (M, T, 2)
        x = self.in_proj(z.reshape(z.shape[0], self.config.plan_tokens, -1)) + self.token_pos
        t, r = (
            packing.pack(torch.broadcast_to(s.reshape(batch, -1), (batch, agents))) for s in (t, r)
        )
        cond = F.silu(self.cond(packing.pack(scene.context)) + self.time(t, r))  # (M, D)
        for block in self.blocks:
            x = block(x, cond, scene, packing)
        shift, scale = self.final_modulation(cond).chunk(2, dim=-1)
        u = self.out(_modulate(self.norm(x), shift, scale))  # (M, N, patch * 2)
        return packing.unpack(u.reshape(-1, steps, channels))  # 0 for padded agents


class RiskFlowGenerator(nn.Module):
    """Scene encoder + MeanFlow head.

    ``encode(batch)`` once per scene batch, then ``average_velocity(z, t, r, scene)``
    as often as needed (the MeanFlow JVP, guidance); ``forward`` does both.
    """

    def __init__(self, config: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = config if config is not None else ModelConfig()
        self.encoder = SceneEncoder(self.config)
        self.head = MeanFlowHead(self.config)

    def encode(self, batch: WindowBatch) -> SceneContext:
        """Context of a batch of windows (``docs/how-to/windows.md``)."""
        return self.encoder(batch)

    def average_velocity(self, z: Tensor, t: Tensor, r: Tensor, scene: SceneContext) -> Tensor:
        """``u_theta(z, t, r; C)``; see :meth:`MeanFlowHead.forward`."""
        expected = (*scene.agent_mask.shape, self.config.future_steps, self.config.action_dim)
        if tuple(z.shape) != expected:
            raise ValueError(f"z must have shape (B, A, T, 2) = {expected}, got {tuple(z.shape)}")
        return self.head(z, t, r, scene)

    def forward(self, batch: WindowBatch, z: Tensor, t: Tensor, r: Tensor) -> Tensor:
        """``u_theta(z, t, r; C(batch))``: ``(B, A, T, 2)``."""
        return self.average_velocity(z, t, r, self.encode(batch))

    def num_parameters(self) -> int:
        """Number of parameters (frozen ones included: a loaded checkpoint is frozen)."""
        return sum(p.numel() for p in self.parameters())

    def checkpoint(self) -> dict[str, Any]:
        """``{"format", "config", "state_dict"}`` for ``torch.save``; tensors on the CPU."""
        state = {k: v.detach().cpu() for k, v in self.state_dict().items()}
        return {"format": CHECKPOINT_FORMAT, "config": self.config.to_dict(), "state_dict": state}

    @classmethod
    def from_checkpoint(
        cls, checkpoint: Mapping[str, Any], config: ModelConfig | None = None
    ) -> RiskFlowGenerator:
        """Rebuild a model from :meth:`checkpoint`'s dict (e.g. after ``torch.load``).

        Args:
            checkpoint: the dict.
            config: optional expected architecture; if given it must equal the
                checkpoint's, field by field.

        Raises:
            CheckpointError: wrong format, a config that differs from ``config`` or is
                invalid, or a state dict with missing, unexpected or mis-shaped tensors.
        """
        if not isinstance(checkpoint, Mapping) or checkpoint.get("format") != CHECKPOINT_FORMAT:
            found = checkpoint.get("format") if isinstance(checkpoint, Mapping) else None
            raise CheckpointError(
                f"checkpoint must be a dict with format {CHECKPOINT_FORMAT!r}, got format {found!r}"
            )
        try:
            saved = ModelConfig.from_dict(checkpoint["config"])
        except (KeyError, TypeError, ValueError) as err:
            raise CheckpointError(f"checkpoint has an invalid ModelConfig: {err}") from None
        if config is not None and config != saved:
            expected, found = config.to_dict(), saved.to_dict()
            diff = {k: (expected[k], found[k]) for k in expected if expected[k] != found[k]}
            raise CheckpointError(
                f"checkpoint ModelConfig differs from the expected one: {{field: (expected, "
                f"checkpoint)}} = {diff}"
            )
        state_dict = checkpoint.get("state_dict")
        if not isinstance(state_dict, Mapping) or not all(
            isinstance(v, Tensor) for v in state_dict.values()
        ):
            raise CheckpointError("checkpoint 'state_dict' must map names to tensors")
        if saved == ModelConfig():  # the shipped architecture: its size is known
            model = cls(saved)
            model.check_checkpoint_state(state_dict)
        else:  # any other: shapes and dtypes first, on the meta device, nothing allocated
            # (costs the import of torch._dynamo, seconds, which meta kernels trigger)
            with torch.device("meta"):
                cls(saved).check_checkpoint_state(state_dict)
            model = cls(saved)
        model.load_state_dict(state_dict)
        return model

    def check_checkpoint_state(self, state_dict: Mapping[str, Tensor]) -> None:
        """CheckpointError listing missing, unexpected, mis-shaped or mis-typed tensors."""
        own = self.state_dict()
        missing = sorted(set(own) - set(state_dict))
        unexpected = sorted(set(state_dict) - set(own))
        shapes = {
            k: (tuple(own[k].shape), tuple(v.shape))
            for k, v in state_dict.items()
            if k in own and tuple(own[k].shape) != tuple(v.shape)
        }
        dtypes = {
            k: (str(own[k].dtype), str(v.dtype))
            for k, v in state_dict.items()
            if k in own and own[k].dtype != v.dtype
        }
        if missing or unexpected or shapes or dtypes:
            raise CheckpointError(
                "checkpoint state dict does not fit the model: "
                f"missing {missing}, unexpected {unexpected}, "
                f"shape mismatches {{name: (model, checkpoint)}} {shapes}, "
                f"dtype mismatches {{name: (model, checkpoint)}} {dtypes}"
            )

    def load_checkpoint_state(self, state_dict: Mapping[str, Tensor]) -> None:
        """``load_state_dict`` after :meth:`check_checkpoint_state` (a
        :class:`CheckpointError` lists every mismatch)."""
        self.check_checkpoint_state(state_dict)
        self.load_state_dict(state_dict)
