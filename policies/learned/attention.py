"""Masked multi-head attention written with plain ``matmul`` / ``softmax``.

Forward-mode AD (``torch.func.jvp``, used by the MeanFlow objective) has no rule for
the fused ``scaled_dot_product_attention`` kernels, so attention is spelled out here.
There is no dropout anywhere in the generator: a JVP must see the same function as
its primal (docs/explanation/method.md), and dropout would draw different masks.

Masking convention: ``mask[..., i, j]`` is True where query ``i`` may attend to key
``j``. A query whose row is entirely False (a padded agent, a history token with no
observation) gets an all-zero output, never NaN: masked scores are filled with the
dtype's most negative finite value (so the softmax stays finite) and the output of
fully masked rows is multiplied by zero.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from policies.learned.embeddings import MLP
from policies.learned.packing import AgentPacking, SceneGroup

# PyTorch's CPU softmax is slow over short rows (13 history or plan tokens: about 5x the
# time of the exp, max and sum it is made of, measured on one thread); rows shorter than
# this are spelled out (the same function, to float rounding).
SHORT_SOFTMAX = 16


def _softmax(scores: Tensor) -> Tensor:
    """``softmax(scores, dim=-1)``; rows shorter than ``SHORT_SOFTMAX`` spelled out."""
    if scores.shape[-1] >= SHORT_SOFTMAX:
        return scores.softmax(dim=-1)
    exp = (scores - scores.amax(dim=-1, keepdim=True)).exp()
    return exp / exp.sum(dim=-1, keepdim=True)


class Attention(nn.Module):
    """Multi-head self-attention over the second-to-last axis, any leading axes.

    ``softmax(q k^T / sqrt(d_head) + bias)`` restricted to ``mask``.
    """

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim ({dim}) must be a multiple of num_heads ({num_heads})")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(
        self,
        x: Tensor,
        mask: Tensor | None = None,
        bias: Tensor | None = None,
        packing: AgentPacking | None = None,
    ) -> Tensor:
        """Attend among the ``L`` tokens of each leading index.

        Args:
            x: ``(..., L, D)`` tokens; with ``packing``, ``(M, N, D)``: the ``N`` tokens
                of each packed real agent, attending across the agents of its scene at
                each token (social attention: ``L`` = the padded agent axis ``A``).
            mask: optional bool ``(..., L, L)`` (broadcastable to it), True = may attend;
                with ``packing``, ``(B, N, A, A)`` (broadcastable).
            bias: optional additive score bias ``(..., H, L, L)`` (broadcastable); with
                ``packing``, ``(B, N, H, A, A)`` (broadcastable).
            packing: the real agents of a padded ``(B, A)`` batch (``packing.py``): the
                projections run on the packed agents, only the scores on a padded layout,
                ``(B_g, N, A_g, A_g)`` for each group of scenes of similar width.

        Returns:
            ``(..., L, D)`` (with ``packing``, ``(M, N, D)``); zero before the output
            projection for queries whose mask row is all False.
        """
        qkv = self.qkv(x)
        if packing is None:
            return self.out(self._attend(qkv, mask, bias))
        parts = []
        for group in packing.groups or (None,):  # scene groups of similar width
            if group is None:
                sub, rows, sub_mask, sub_bias = packing, qkv, mask, bias
            else:
                sub, rows = group.packing, qkv[group.rows]
                sub_mask, sub_bias = _group_scenes(mask, group), _group_scenes(bias, group)
            scenes = sub.unpack(rows).transpose(1, 2)  # (B_g, N, A_g, 3 D)
            parts.append(sub.pack(self._attend(scenes, sub_mask, sub_bias).transpose(1, 2)))
        out = parts[0] if packing.order is None else torch.cat(parts)[packing.order]
        return self.out(out)

    def _attend(self, qkv: Tensor, mask: Tensor | None, bias: Tensor | None) -> Tensor:
        """``(..., L, 3 D)`` projected tokens -> ``(..., L, D)`` mixed values."""
        *lead, length, _ = qkv.shape
        qkv = qkv.reshape(*lead, length, 3, self.num_heads, self.head_dim)
        q, k, v = (qkv.select(-3, i).transpose(-2, -3) for i in range(3))  # (..., H, L, dh)
        scores = (q @ k.transpose(-1, -2)) * self.head_dim**-0.5  # (..., H, L, L)
        if bias is not None:
            scores = scores + bias
        if mask is not None:
            mask = mask[..., None, :, :]  # broadcast over heads
            scores = scores.masked_fill(~mask, torch.finfo(scores.dtype).min)
        weights = _softmax(scores)
        if mask is not None:
            weights = weights * mask.any(dim=-1, keepdim=True).to(weights.dtype)
        return (
            (weights @ v).transpose(-2, -3).reshape(*lead, length, self.num_heads * self.head_dim)
        )


def _group_scenes(x: Tensor | None, group: SceneGroup) -> Tensor | None:
    """A mask or bias ``(B, ..., A, A)`` cut to a scene group's ``(B_g, ..., A_g, A_g)``."""
    if x is None:
        return None
    keep = slice(0, group.width)
    return (x if x.shape[0] == 1 else x[group.scenes])[..., keep, keep]


class TransformerBlock(nn.Module):
    """Pre-LayerNorm block: ``x + Attn(LN(x))``, then ``x + MLP(LN(x))``."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = MLP(dim, mlp_ratio * dim, dim)

    def forward(
        self,
        x: Tensor,
        mask: Tensor | None = None,
        bias: Tensor | None = None,
        packing: AgentPacking | None = None,
    ) -> Tensor:
        """Args and returns as :meth:`Attention.forward`."""
        x = x + self.attn(self.norm1(x), mask, bias, packing)
        return x + self.mlp(self.norm2(x))


def social_mask(pair_mask: Tensor, agent_mask: Tensor) -> Tensor:
    """Which agents each agent attends to in social attention.

    Args:
        pair_mask: ``(B, A, A)`` bool, pairs that exist and lie within 50 m (False on
            the diagonal, see ``riskflow_env.risk.pairwise_features``).
        agent_mask: ``(B, A)`` bool, agents that exist at the current step.

    Returns:
        ``(B, A, A)`` bool: ``pair_mask`` plus self-attention of every existing agent;
        rows and columns of padded agents are all False.
    """
    eye = torch.eye(pair_mask.shape[-1], dtype=torch.bool, device=pair_mask.device)
    both = agent_mask[..., :, None] & agent_mask[..., None, :]
    return (pair_mask | eye) & both


def edge_bias(edges: Tensor, projection: nn.Linear) -> Tensor:
    """Per-head additive bias ``b(e_ij)`` of social attention.

    Args:
        edges: ``(B, A, A, E)`` pair embeddings ``MLP(e_ij)``.
        projection: ``Linear(E, H)``.

    Returns:
        ``(B, 1, H, A, A)``: broadcast over the token axis of ``(B, N, A, D)`` tokens.
    """
    return projection(edges).permute(0, 3, 1, 2)[:, None]
