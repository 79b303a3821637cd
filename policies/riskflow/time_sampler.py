"""Sampling of the MeanFlow time pair ``(t, r)``, ``0 <= t <= r <= 1``.

MeanFlow (Geng et al. 2025, section 4.3 and table 1c) draws two times from a
logit-normal distribution, ``sigmoid(N(mean, std^2))`` with ``(mean, std) = (-0.4,
1.0)``, sorts them, and sets ``r = t`` for a fraction of the samples; those are plain
flow-matching samples (``u(z, t, t) = v(z, t)``), which anchor the instantaneous
velocity. In this project's convention noise is at ``t = 0`` and data at ``t = 1``,
so the sorted pair is ``t <= r`` (MeanFlow's own code, with data at 0, has ``r <= t``).
RiskFlow uses ``r = t`` with probability 0.2 (docs/explanation/method.md).

The sampler calls the model at one pair only, ``(t, r) = (0, 1)`` (one step from pure
noise), which the logit-normal draws almost never come near (about 1% of pairs have
``t < 0.05``, under 0.1% have ``r > 0.95``). ``one_step_fraction`` sets that share of
pairs to exactly ``(0, 1)``, so the loss (and its realism penalties) sees the plan the
sampler makes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class TimeSampler:
    """Logit-normal ``(t, r)`` pairs.

    Attributes:
        mean: mean of ``logit(t)`` before sorting.
        std: standard deviation of ``logit(t)`` before sorting.
        equal_fraction: probability that a sample has ``r = t`` (independent draws).
        flow_matching: if True, ``r = t`` always (the plain flow-matching reference;
            no JVP is needed then, see ``meanflow.flow_matching_loss``).
        one_step_fraction: probability that a sample is the sampler's own call
            ``(t, r) = (0, 1)`` (independent draws, after the ``r = t`` ones); 0 draws no
            extra random numbers, so the default keeps earlier runs' times bit for bit.
    """

    mean: float = -0.4
    std: float = 1.0
    equal_fraction: float = 0.2
    flow_matching: bool = False
    one_step_fraction: float = 0.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.mean):
            raise ValueError(f"TimeSampler.mean must be finite, got {self.mean}")
        if not (math.isfinite(self.std) and self.std > 0):
            raise ValueError(f"TimeSampler.std must be finite and > 0, got {self.std}")
        if not 0.0 <= self.equal_fraction <= 1.0:
            raise ValueError(
                f"TimeSampler.equal_fraction must be in [0, 1], got {self.equal_fraction}"
            )
        if not 0.0 <= self.one_step_fraction <= 1.0:
            raise ValueError(
                f"TimeSampler.one_step_fraction must be in [0, 1], got {self.one_step_fraction}"
            )
        if self.flow_matching and self.one_step_fraction:
            raise ValueError(
                "TimeSampler.one_step_fraction must be 0 with flow_matching (r = t always)"
            )

    def __call__(
        self,
        batch_size: int,
        *,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> tuple[Tensor, Tensor]:
        """Draw ``batch_size`` pairs.

        Args:
            batch_size: number of pairs (one per scene of a batch).
            generator: random source (on ``device``); the global one if None.
            device: device of the result.
            dtype: floating dtype of the result.

        Returns:
            ``t, r``: ``(batch_size,)`` each, ``0 < t <= r < 1``, except the
            ``one_step_fraction`` share that is exactly ``(0, 1)``.
        """
        if batch_size < 0:
            raise ValueError(f"batch_size must be >= 0, got {batch_size}")
        normal = torch.randn(2, batch_size, generator=generator, device=device, dtype=dtype)
        times = torch.sigmoid(self.mean + self.std * normal)
        if self.flow_matching:
            return times[0], times[0].clone()
        t, r = times.min(dim=0).values, times.max(dim=0).values
        uniform = torch.rand(batch_size, generator=generator, device=device, dtype=dtype)
        r = torch.where(uniform < self.equal_fraction, t, r)
        if self.one_step_fraction:
            one_step = (
                torch.rand(batch_size, generator=generator, device=device, dtype=dtype)
                < self.one_step_fraction
            )
            t = torch.where(one_step, 0.0, t)
            r = torch.where(one_step, 1.0, r)
        return t, r
