"""Unguided reverse chains (DDPM, DDIM) and the one-call sampler view of a denoiser.

A chain starts from ``x_{K-1} = noise[0]`` and takes the transitions of
``DiffusionSchedule.levels(sampling_steps)``: every one of the ``K`` levels (DDPM, ``eta
= 1``) or ``S < K`` evenly spaced ones (DDIM; ``eta = 0`` deterministic). Transition
``i`` adds ``sigma_i * noise[i + 1]``; all the noise is drawn up front
(:func:`chain_noise`), so a seed fixes the plans. The scene is encoded once per chain.

:class:`OneCallSampler` makes a denoiser look like a one-step generator
(``average_velocity(eps, 0, 1; C) = chain(eps) - eps`` with deterministic DDIM), so
``policies.learned.sampler.sample`` and ``policies.learned.validation.evaluate`` (the
validation of ``riskflow-train``) work on it unchanged.
"""

from __future__ import annotations

import torch
from torch import Tensor

from policies.baselines.diffusion.model import DiffusionDenoiser
from policies.learned.encoder import SceneContext

Levels = list[tuple[int, int]]


def chain_noise(
    shape: tuple[int, ...],
    levels: Levels,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """``(len(levels) + 1, *shape)`` standard normal: the start and each transition's noise."""
    return torch.randn((len(levels) + 1, *shape), generator=generator, device=device, dtype=dtype)


def denoise_step(
    denoiser: DiffusionDenoiser, x: Tensor, k: int, k_prev: int, eta: float, scene: SceneContext
) -> tuple[Tensor, Tensor, Tensor, float]:
    """``(x0_hat, eps_hat, mean, sigma)`` of one transition (``schedule.reverse_moments``)."""
    x0_hat, eps_hat = denoiser(x, k, scene, clip=True)
    mean, sigma = denoiser.schedule.reverse_moments(x0_hat, eps_hat, k, k_prev, eta)
    return x0_hat, eps_hat, mean, sigma


@torch.no_grad()
def reverse_chain(
    denoiser: DiffusionDenoiser,
    scene: SceneContext,
    noise: Tensor,
    levels: Levels,
    eta: float = 1.0,
) -> list[Tensor]:
    """Run a chain; returns its path ``[x_start, x after transition 1, ..., x0]``.

    Args:
        denoiser: the denoiser.
        scene: ``denoiser.encode(batch)``.
        noise: ``(len(levels) + 1, B, A, T, 2)`` from :func:`chain_noise`.
        levels: ``denoiser.schedule.levels(...)``.
        eta: DDIM stochasticity (1 with every level: DDPM).
    """
    if noise.shape[0] != len(levels) + 1:
        raise ValueError(
            f"noise must have len(levels) + 1 = {len(levels) + 1} rows, got {noise.shape[0]}"
        )
    path = [noise[0]]
    for index, (k, k_prev) in enumerate(levels):
        _, _, mean, sigma = denoise_step(denoiser, path[-1], k, k_prev, eta, scene)
        path.append(mean + sigma * noise[index + 1])
    return path


class OneCallSampler:
    """A denoiser as a one-step generator: deterministic DDIM (``eta = 0``) from ``eps``.

    Args:
        denoiser: the denoiser.
        sampling_steps: DDIM levels (None: all ``K``).
    """

    def __init__(self, denoiser: DiffusionDenoiser, sampling_steps: int | None = 10) -> None:
        self.denoiser = denoiser
        self.levels = denoiser.schedule.levels(sampling_steps)
        self.config = denoiser.config

    def to(self, device: torch.device | str) -> OneCallSampler:
        """Move the denoiser's network to ``device`` (in place, like ``nn.Module.to``)."""
        self.denoiser.network.to(device)
        return self

    def eval(self) -> OneCallSampler:
        """Put the denoiser's network in eval mode (in place)."""
        self.denoiser.network.eval()
        return self

    def encode(self, batch) -> SceneContext:
        """The denoiser's scene context."""
        return self.denoiser.encode(batch)

    def average_velocity(self, z: Tensor, t: Tensor, r: Tensor, scene: SceneContext) -> Tensor:
        """``chain(z) - z`` (``t, r`` are ignored: the chain always goes noise -> data)."""
        noise = torch.zeros((len(self.levels) + 1, *z.shape), dtype=z.dtype, device=z.device)
        noise[0] = z
        return reverse_chain(self.denoiser, scene, noise, self.levels, eta=0.0)[-1] - z


__all__ = [
    "OneCallSampler",
    "chain_noise",
    "denoise_step",
    "reverse_chain",
]
