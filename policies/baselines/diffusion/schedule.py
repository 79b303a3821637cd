"""DDPM noise schedule and the DDPM / DDIM reverse transitions in closed form.

Notation (Ho et al. 2020, "Denoising Diffusion Probabilistic Models"; Song et al. 2021,
"Denoising Diffusion Implicit Models"): levels ``k = 0 .. K-1`` (``K = num_steps``, 100
as in CTG, Zhong et al. 2023), ``beta_k``, ``alpha_k = 1 - beta_k``,
``alpha_bar_k = prod_{j <= k} alpha_j``, and the forward marginal

    q(x_k | x_0) = N(sqrt(alpha_bar_k) x_0, (1 - alpha_bar_k) I).

Level ``K - 1`` is (almost) pure noise, level 0 the least noisy; "level -1" is the clean
sample (``alpha_bar = 1``). A reverse transition goes from level ``k`` to an earlier level
``k_prev < k`` (``k - 1`` for DDPM, a subsequence for DDIM). Given the denoiser's
estimates ``x0_hat`` and ``eps_hat`` (either one determines the other at ``x_k``), DDIM
(Song et al. 2021, eq. 12) gives

    x_{k_prev} = sqrt(ab') x0_hat + sqrt(1 - ab' - sigma^2) eps_hat + sigma z,
    sigma = eta sqrt((1 - ab') / (1 - ab)) sqrt(1 - ab / ab'),

with ``ab = alpha_bar_k``, ``ab' = alpha_bar_{k_prev}``. ``eta = 1`` on consecutive levels
*is* the DDPM ancestral step (its mean is the posterior mean of ``q(x_{k-1} | x_k, x_0)``
and ``sigma^2`` the posterior variance ``beta~_k``); ``eta = 0`` is deterministic DDIM.
The schedule is a set of float64 tables; every function casts to the input's dtype.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from riskflow_env.config import is_integer

SCHEDULES = ("cosine", "linear")
COSINE_OFFSET = 0.008  # s of the cosine schedule (Nichol & Dhariwal 2021)
MAX_BETA = 0.999  # betas are clipped here (the cosine schedule's last level)


@dataclass(frozen=True)
class ScheduleConfig:
    """The forward process.

    Attributes:
        num_steps: ``K`` noise levels (100 as in CTG / CTG++).
        kind: ``"cosine"`` (Nichol & Dhariwal 2021; the tbsim diffuser's) or ``"linear"``.
        beta_start: first beta of the linear schedule at ``K = 1000`` (Ho et al. 2020);
            the betas are scaled by ``1000 / K`` so that any ``K`` reaches noise.
        beta_end: last beta of the linear schedule at ``K = 1000``.
    """

    num_steps: int = 100
    kind: str = "cosine"
    beta_start: float = 1e-4
    beta_end: float = 0.02

    def __post_init__(self) -> None:
        if not (is_integer(self.num_steps) and self.num_steps >= 1):
            raise ValueError(f"ScheduleConfig.num_steps must be an int >= 1, got {self.num_steps}")
        object.__setattr__(self, "num_steps", int(self.num_steps))  # a numpy int as a Python one
        if self.kind not in SCHEDULES:
            raise ValueError(f"ScheduleConfig.kind must be one of {SCHEDULES}, got {self.kind!r}")
        if not 0 < self.beta_start <= self.beta_end < 1:
            raise ValueError(
                "ScheduleConfig needs 0 < beta_start <= beta_end < 1, got "
                f"{self.beta_start}, {self.beta_end}"
            )


class DiffusionSchedule:
    """Tables of a :class:`ScheduleConfig` and the closed-form forward / reverse moments."""

    def __init__(self, config: ScheduleConfig | None = None) -> None:
        self.config = config or ScheduleConfig()
        steps = self.config.num_steps
        if self.config.kind == "cosine":
            grid = torch.arange(steps + 1, dtype=torch.float64) / steps
            f = torch.cos((grid + COSINE_OFFSET) / (1 + COSINE_OFFSET) * math.pi / 2) ** 2
            betas = (1 - f[1:] / f[:-1]).clamp(max=MAX_BETA)
        else:  # scaled to K (Nichol & Dhariwal 2021): the 1000-step DDPM betas for K = 1000
            scale = 1000.0 / steps
            start, end = scale * self.config.beta_start, min(scale * self.config.beta_end, MAX_BETA)
            betas = torch.linspace(min(start, end), end, steps, dtype=torch.float64)
        self.betas = betas
        self.alphas = 1.0 - betas
        self.alpha_bar = torch.cumprod(self.alphas, dim=0)
        self.alpha_bar_prev = torch.cat([torch.ones(1, dtype=torch.float64), self.alpha_bar[:-1]])
        # beta~_k, the variance of q(x_{k-1} | x_k, x_0) (Ho et al. 2020, eq. 7).
        self.posterior_variance = betas * (1 - self.alpha_bar_prev) / (1 - self.alpha_bar)

    @property
    def num_steps(self) -> int:
        """``K``."""
        return self.config.num_steps

    def _at(self, table: Tensor, k: Tensor | int, like: Tensor) -> Tensor:
        """``table[k]`` shaped to broadcast over ``like (B, ...)`` (``k`` int or ``(B,)``);
        ``k = -1`` reads ``alpha_bar = 1`` (the clean level) from ``alpha_bar`` tables."""
        k = torch.as_tensor(k, device=table.device)
        padded = torch.cat([table, torch.ones(1, dtype=table.dtype)])  # index -1: clean
        values = padded[k].to(device=like.device, dtype=like.dtype)
        return values.reshape(*values.shape, *([1] * (like.dim() - values.dim())))

    def q_moments(self, k: Tensor | int, like: Tensor) -> tuple[Tensor, Tensor]:
        """``(sqrt(alpha_bar_k), sqrt(1 - alpha_bar_k))``: mean scale and std of ``q(x_k|x_0)``."""
        alpha_bar = self._at(self.alpha_bar, k, like)
        return alpha_bar.sqrt(), (1 - alpha_bar).sqrt()

    def q_sample(self, x0: Tensor, k: Tensor | int, noise: Tensor) -> Tensor:
        """``x_k = sqrt(alpha_bar_k) x0 + sqrt(1 - alpha_bar_k) noise``; ``k`` int or ``(B,)``."""
        scale, std = self.q_moments(k, x0)
        return scale * x0 + std * noise

    def x0_from_eps(self, x_k: Tensor, k: Tensor | int, eps: Tensor) -> Tensor:
        """The clean sample that ``x_k`` and ``eps`` imply."""
        scale, std = self.q_moments(k, x_k)
        return (x_k - std * eps) / scale

    def eps_from_x0(self, x_k: Tensor, k: Tensor | int, x0: Tensor) -> Tensor:
        """The noise that ``x_k`` and ``x0`` imply."""
        scale, std = self.q_moments(k, x_k)
        return (x_k - scale * x0) / std

    def posterior(self, x0: Tensor, x_k: Tensor, k: int) -> tuple[Tensor, Tensor]:
        """Mean and variance of ``q(x_{k-1} | x_k, x_0)`` (Ho et al. 2020, eq. 7)."""
        alpha_bar, alpha_bar_prev = self.alpha_bar[k], self.alpha_bar_prev[k]
        coef_x0 = alpha_bar_prev.sqrt() * self.betas[k] / (1 - alpha_bar)
        coef_xk = self.alphas[k].sqrt() * (1 - alpha_bar_prev) / (1 - alpha_bar)
        mean = float(coef_x0) * x0 + float(coef_xk) * x_k
        return mean, x_k.new_tensor(float(self.posterior_variance[k]))

    def reverse_moments(
        self, x0_hat: Tensor, eps_hat: Tensor, k: int, k_prev: int, eta: float
    ) -> tuple[Tensor, float]:
        """Mean and std of the DDIM transition ``k -> k_prev`` (module docstring).

        Args:
            x0_hat: the clean estimate at level ``k``.
            eps_hat: the noise estimate at level ``k``, like ``x0_hat``.
            k: current level in ``[0, K)``.
            k_prev: target level in ``[-1, k)``; -1 is the clean sample (std 0).
            eta: 0 deterministic DDIM, 1 DDPM-like (exactly DDPM for ``k_prev = k - 1``).
        """
        if not (0 <= k < self.num_steps and -1 <= k_prev < k):
            raise ValueError(
                f"need 0 <= k < {self.num_steps} and -1 <= k_prev < k, got {k}, {k_prev}"
            )
        alpha_bar = float(self.alpha_bar[k])
        alpha_bar_prev = 1.0 if k_prev < 0 else float(self.alpha_bar[k_prev])
        variance = (1 - alpha_bar_prev) / (1 - alpha_bar) * (1 - alpha_bar / alpha_bar_prev)
        sigma = eta * math.sqrt(max(variance, 0.0))
        direction = math.sqrt(max(1 - alpha_bar_prev - sigma**2, 0.0))
        return math.sqrt(alpha_bar_prev) * x0_hat + direction * eps_hat, sigma

    def levels(self, sampling_steps: int | None = None) -> list[tuple[int, int]]:
        """The ``(k, k_prev)`` transitions of a reverse chain, noisiest first.

        Args:
            sampling_steps: None or ``K``: every level (DDPM); fewer: DDIM on evenly
                spaced levels ``round(linspace(K - 1, 0, S))``.
        """
        steps = self.num_steps if sampling_steps is None else sampling_steps
        if not (is_integer(steps) and 1 <= steps <= self.num_steps):
            raise ValueError(f"sampling_steps must be an int in [1, {self.num_steps}], got {steps}")
        ks = torch.linspace(self.num_steps - 1, 0, steps, dtype=torch.float64).round().long()
        ks = [int(k) for k in ks]
        return list(zip(ks, ks[1:] + [-1], strict=True))


__all__ = ["SCHEDULES", "DiffusionSchedule", "ScheduleConfig"]
