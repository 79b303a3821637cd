"""The real agents of a padded batch, packed: per-agent layers skip the padded slots.

A :class:`~policies.learned.window_types.WindowBatch` pads every scene's agent axis to
the largest scene of the batch. Everything the network does to one agent alone (history
tokens, temporal attention, MLPs, modulation, the map CNN) runs on the packed real agents
``(M, ...)``, ``M = sum_b A_b``; only the agent-agent (social) attention of a scene needs
the padded ``(B, A, ...)`` layout, and :class:`AgentPacking` moves between the two.
Social attention costs ``A^2`` per scene and token: scenes sorted by width are split into
at most ``MAX_SCENE_GROUPS`` groups of at least ``MIN_GROUP_SCENES`` scenes
(:class:`SceneGroup`), each padded only to its own widest scene (a loop over these few
groups, not over scenes).

Planning groups scenes by their exact width instead (:func:`exact_scene_widths`, which
the planning cycle runs under): every scene's social attention then has the shape it has
alone, so a scene planned in a batch gets the network outputs it gets alone, bit for bit
(padding to another width changes the reductions' rounding). It costs one attention call
per distinct width; training keeps the few groups of similar width.

Gathering and scattering are ``index_select`` / ``index_copy``: differentiable in both
modes (the MeanFlow objective's ``torch.func.jvp`` goes through them).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

MAX_SCENE_GROUPS = 3  # groups of scenes of similar width in social attention
# Scenes per group at least: smaller groups cost more in per-call overhead than they save
# (measured on one CPU thread: a gain at B = 32, a loss at B = 8 in three groups).
MIN_GROUP_SCENES = 8
_EXACT_WIDTHS = ContextVar("exact_scene_widths", default=False)


@contextmanager
def exact_scene_widths() -> Iterator[None]:
    """Within it, :meth:`AgentPacking.from_mask` groups scenes by exact width (module
    docstring)."""
    token = _EXACT_WIDTHS.set(True)
    try:
        yield
    finally:
        _EXACT_WIDTHS.reset(token)


@dataclass(frozen=True)
class SceneGroup:
    """Scenes of similar width whose social attention runs together.

    Attributes:
        scenes: ``(B_g,)`` batch index of each scene of the group.
        width: ``A_g`` agent slots kept (the group's largest last real slot + 1).
        packing: the group's own packing of its ``(B_g, A_g)`` slots.
        rows: ``(M_g,)`` row of each of the group's real agents (in the group's order) in
            the whole batch's packed order.
    """

    scenes: Tensor
    width: int
    packing: AgentPacking
    rows: Tensor


@dataclass(frozen=True)
class AgentPacking:
    """Which slots of a ``(B, A)`` batch hold real agents (row-major order).

    Attributes:
        index: ``(M,)`` flat slot ``b * A + a`` of each real agent; None when every slot
            is real (packing is then a reshape).
        batch_size: ``B``.
        num_agents: ``A``, the padded agent axis.
        groups: the scene groups of social attention; empty: one group, the whole batch.
        order: ``(M,)`` where each packed row is in the concatenated rows of ``groups``.
    """

    index: Tensor | None
    batch_size: int
    num_agents: int
    groups: tuple[SceneGroup, ...] = ()
    order: Tensor | None = None

    @classmethod
    def from_mask(cls, agent_mask: Tensor, grouped: bool = True) -> AgentPacking:
        """Args: ``agent_mask (B, A)`` bool, the real agents; ``grouped``: also split the
        scenes into :class:`SceneGroup` s of similar width."""
        batch_size, num_agents = agent_mask.shape
        if bool(agent_mask.all()):
            return cls(None, batch_size, num_agents)
        index = agent_mask.reshape(-1).nonzero()[:, 0]
        slot = torch.arange(1, num_agents + 1, device=agent_mask.device)
        widths = (agent_mask * slot).amax(dim=1).tolist()  # last real slot + 1
        exact = _EXACT_WIDTHS.get()
        num_groups = (
            len(set(widths)) if exact else min(MAX_SCENE_GROUPS, batch_size // MIN_GROUP_SCENES)
        )
        if not grouped or num_groups < 2 or len(set(widths)) == 1:
            return cls(index, batch_size, num_agents)
        position = (agent_mask.reshape(-1).cumsum(0) - 1).reshape(batch_size, num_agents)
        groups = []
        order = np.argsort(widths, kind="stable")
        if exact:  # one group per width
            cuts = np.flatnonzero(np.diff(np.asarray(widths)[order])) + 1
            chunks = np.split(order, cuts)
        else:
            chunks = np.array_split(order, num_groups)
        for chunk in (c for c in chunks if len(c)):
            scenes = torch.as_tensor(np.sort(chunk), device=agent_mask.device)
            width = max(widths[b] for b in chunk.tolist())
            mask = agent_mask[scenes, :width]
            packing = cls.from_mask(mask, grouped=False)
            groups.append(SceneGroup(scenes, width, packing, position[scenes, :width][mask]))
        order = torch.cat([group.rows for group in groups]).argsort()
        return cls(index, batch_size, num_agents, tuple(groups), order)

    def pack(self, x: Tensor) -> Tensor:
        """``(B, A, ...) -> (M, ...)``: the real agents' rows."""
        flat = x.reshape(self.batch_size * self.num_agents, *x.shape[2:])
        return flat if self.index is None else flat.index_select(0, self.index)

    def unpack(self, x: Tensor) -> Tensor:
        """``(M, ...) -> (B, A, ...)``: the rows back in their slots, zero in padded ones."""
        if self.index is not None:
            flat = x.new_zeros(self.batch_size * self.num_agents, *x.shape[1:])
            x = flat.index_copy(0, self.index, x)
        return x.reshape(self.batch_size, self.num_agents, *x.shape[1:])


__all__ = ["AgentPacking", "exact_scene_widths"]
