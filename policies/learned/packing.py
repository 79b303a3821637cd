"""The real agents of a padded batch, packed: per-agent layers skip the padded slots.

A :class:`~policies.learned.window_types.WindowBatch` pads every scene's agent axis to
the largest scene of the batch. Everything the network does to one agent alone (history
tokens, temporal attention, MLPs, modulation, the map CNN) runs on the packed real agents
``(M, ...)``, ``M = sum_b A_b``; only the agent-agent (social) attention of a scene needs
the padded ``(B, A, ...)`` layout, and :class:`AgentPacking` moves between the two.

Gathering and scattering are ``index_select`` / ``index_copy``: differentiable in both
modes (the MeanFlow objective's ``torch.func.jvp`` goes through them).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass(frozen=True)
class AgentPacking:
    """Which slots of a ``(B, A)`` batch hold real agents (row-major order).

    Attributes:
        index: ``(M,)`` flat slot ``b * A + a`` of each real agent; None when every slot
            is real (packing is then a reshape).
        batch_size: ``B``.
        num_agents: ``A``, the padded agent axis.
    """

    index: Tensor | None
    batch_size: int
    num_agents: int

    @classmethod
    def from_mask(cls, agent_mask: Tensor) -> AgentPacking:
        """Args: ``agent_mask (B, A)`` bool, the real agents."""
        batch_size, num_agents = agent_mask.shape
        index = None if bool(agent_mask.all()) else agent_mask.reshape(-1).nonzero()[:, 0]
        return cls(index, batch_size, num_agents)

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


__all__ = ["AgentPacking"]
