"""Data-parallel training over processes started by ``torchrun`` (``torch.distributed``).

Every process holds the whole model and the whole window set, walks the same seeded batch
order and draws the same noise (the draws of the global batch, from one seeded generator);
each takes its :class:`Shard`, a contiguous share of the rows of every global batch.
After the backward pass the gradients are averaged over the processes
(:func:`average_gradients`), so every process takes the same optimiser step and keeps
the same weights; only the main process (rank 0) validates and writes.

Exactness. The losses are means over valid entries (agent-steps, actions, box pairs),
so the shards' own means, averaged, would weigh a shard with few valid entries as much
as one with many. Inside :func:`global_means` every such mean (:func:`masked_mean`)
divides by the count summed over all processes instead (times their number): the
averaged gradient is then the gradient of the global batch's loss, and a run on N
processes gives the weights of one process with the same ``--batch-size`` up to
floating-point rounding (``tests/policies/learned/test_distributed.py``).

Why an explicit ``all_reduce`` and not ``DistributedDataParallel``: the objectives call
the network's methods (``encode``, ``average_velocity``) inside ``torch.func.jvp``, not its
``forward``, which DDP's reducer hooks into; and the model is small (its gradient is one
all-reduce of a few MB after the backward pass, which DDP would only overlap with it).
The parameters stay those of the plain model, so checkpoints are the same files.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import Tensor

ENV_WORLD, ENV_RANK, ENV_LOCAL_RANK = "WORLD_SIZE", "RANK", "LOCAL_RANK"  # set by torchrun


@dataclass(frozen=True)
class Shard:
    """Rows ``start:stop`` of a global batch of ``total`` windows: one process's share."""

    start: int
    stop: int
    total: int

    def rows(self, draws: Tensor) -> Tensor:
        """This shard's rows of ``draws``, drawn for the whole global batch (leading axis)."""
        return draws[self.start : self.stop]


@dataclass(frozen=True)
class Ranks:
    """This process's place among the training processes (one process: the defaults)."""

    rank: int = 0
    world: int = 1
    local: int = 0
    """rank among the processes of this machine"""

    @property
    def main(self) -> bool:
        """Whether this process validates and writes checkpoints and logs (rank 0)."""
        return self.rank == 0

    def shard(self, total: int) -> Shard:
        """This process's rows of a global batch of ``total`` windows (contiguous; the
        first ``total % world`` processes take one row more)."""
        size, extra = divmod(total, self.world)
        start = self.rank * size + min(self.rank, extra)
        return Shard(start, start + size + (self.rank < extra), total)


def backend(device: str | torch.device) -> str:
    """The collective backend of ``device``: NCCL for CUDA, gloo for the CPU."""
    return "nccl" if torch.device(device).type == "cuda" else "gloo"


def process_device(device: str, ranks: Ranks) -> str:
    """``device`` of this process: ``cuda`` becomes ``cuda:LOCAL_RANK`` (one GPU per
    process); a given GPU index with several processes is an error naming ``--device``."""
    kind = torch.device(device)
    if ranks.world == 1 or kind.type != "cuda":
        return device
    if kind.index is not None:
        raise ValueError(
            f"--device: give 'cuda' (each process takes cuda:LOCAL_RANK), not {device!r}, "
            f"with {ranks.world} processes"
        )
    return f"cuda:{ranks.local}"


@contextlib.contextmanager
def process_group(device: str) -> Iterator[Ranks]:
    """This process's :class:`Ranks` while training on ``device``.

    A group initialised by the caller is used as it is; under ``torchrun``
    (``WORLD_SIZE`` > 1) the group is joined here, with :func:`backend`'s backend, and
    left at exit; otherwise this is the one process (``Ranks()``).
    """
    if dist.is_available() and dist.is_initialized():
        rank = dist.get_rank()
        yield Ranks(rank, dist.get_world_size(), int(os.environ.get(ENV_LOCAL_RANK, rank)))
        return
    if int(os.environ.get(ENV_WORLD, "1")) <= 1:
        yield Ranks()
        return
    ranks = Ranks(*(int(os.environ[name]) for name in (ENV_RANK, ENV_WORLD, ENV_LOCAL_RANK)))
    local = process_device(device, ranks)
    if torch.device(local).type == "cuda":
        torch.cuda.set_device(local)
    dist.init_process_group(backend(local))
    try:
        yield ranks
    finally:
        dist.destroy_process_group()


_SHARED_COUNTS = [1]  # processes whose masked means form one global mean (1: off)


@contextlib.contextmanager
def global_means(ranks: Ranks) -> Iterator[None]:
    """Within the block, :func:`masked_mean` divides by counts summed over ``ranks``
    (every process must compute the same means in the same order: one training loss)."""
    _SHARED_COUNTS.append(ranks.world)
    try:
        yield
    finally:
        _SHARED_COUNTS.pop()


def masked_mean(total: Tensor, count: Tensor) -> Tensor:
    """``total / max(count, 1)``: a masked sum over its number of valid entries.

    Inside :func:`global_means` with N processes: ``N * total / max(sum of the processes'
    counts, 1)``, whose average over the processes is the global batch's mean.
    """
    world = _SHARED_COUNTS[-1]
    if world == 1:
        return total / count.clamp(min=1)
    count = count.detach().clone()
    dist.all_reduce(count)
    return total * world / count.clamp(min=1)


def broadcast_parameters(module: torch.nn.Module, ranks: Ranks) -> None:
    """Give every process rank 0's parameters and buffers."""
    if ranks.world > 1:
        for tensor in [*module.parameters(), *module.buffers()]:
            dist.broadcast(tensor.data, src=0)


def average_gradients(parameters: Iterable[torch.nn.Parameter], ranks: Ranks) -> None:
    """Replace each gradient by its mean over the processes (one ``all_reduce``); a
    parameter that has a gradient on no process keeps ``None``, as on one process."""
    if ranks.world == 1:
        return
    parameters = list(parameters)
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in parameters]
    has = [float(p.grad is not None) for p in parameters]
    flat = torch.cat([g.reshape(-1) for g in grads] + [grads[0].new_tensor(has)])
    dist.all_reduce(flat)
    flat /= ranks.world
    offset = 0
    for parameter in parameters:
        size = parameter.numel()
        parameter.grad = flat[offset : offset + size].view_as(parameter).clone()
        offset += size
    for parameter, present in zip(parameters, flat[offset:].tolist(), strict=True):
        if present == 0:
            parameter.grad = None


def average_values(values: dict[str, Tensor | float], ranks: Ranks) -> dict[str, float]:
    """``values`` (scalars, the same keys on every process) averaged over the processes."""
    if ranks.world == 1:
        return {key: float(value) for key, value in values.items()}
    stacked = torch.tensor([float(value) for value in values.values()], dtype=torch.float64)
    stacked = _on_backend(stacked)
    dist.all_reduce(stacked)
    return dict(zip(values, (stacked / ranks.world).tolist(), strict=True))


def any_process(flag: bool, ranks: Ranks) -> bool:
    """Whether ``flag`` holds on any process (all agree: e.g. to stop at a time budget)."""
    if ranks.world == 1:
        return flag
    value = _on_backend(torch.tensor([float(flag)]))
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item())


@contextlib.contextmanager
def main_first(ranks: Ranks) -> Iterator[None]:
    """The block runs on the main process first (e.g. writing the window caches), then on
    the first process of each other machine (which writes them where the folder is not
    shared), then on the rest (which read them): never two writers of one file at once."""
    if ranks.world == 1:
        yield
        return
    turn = 0 if ranks.main else 1 if ranks.local == 0 else 2
    for stage in range(3):
        if stage == turn:
            yield
        if stage < 2:
            dist.barrier()


def _on_backend(tensor: Tensor) -> Tensor:
    """``tensor`` where the group's backend reduces it (NCCL: the current GPU)."""
    if dist.get_backend() == "nccl":
        return tensor.to(torch.device("cuda", torch.cuda.current_device()))
    return tensor


__all__ = [
    "Ranks",
    "Shard",
    "any_process",
    "average_gradients",
    "average_values",
    "backend",
    "broadcast_parameters",
    "global_means",
    "main_first",
    "masked_mean",
    "process_device",
    "process_group",
]
