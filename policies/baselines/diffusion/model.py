"""The action-space denoiser of the diffusion baselines: RiskFlow's network, reused.

CTG (Zhong et al. 2023, "Guided Conditional Diffusion for Controllable Traffic
Simulation") and CTG++ (Zhong et al. 2023, "Language-Guided Traffic Simulation via
Scene-Level Diffusion") denoise future trajectories with a transformer over the scene
context. Here the denoiser *is* :class:`~policies.learned.generator.RiskFlowGenerator`
(same scene encoder, same adaLN-Zero head with temporal and social attention), with the
MeanFlow time pair ``(t, r)`` replaced by the diffusion level: ``t = r = tau_k`` with
``tau_k = 1 - (k + 1) / K`` (noise near 0, data near 1, as in this project's flow
convention), so the interval embedding is constant and the time embedding tells the
level. The head's output ``out = net(x_k, k; C)`` is read as (``a = sqrt(alpha_bar_k)``,
``s = sqrt(1 - alpha_bar_k)``)

* ``prediction="v"`` (default; Salimans & Ho 2022): ``out`` is ``v = a eps - s x0``, so
  ``x0_hat = a x_k - s out`` and ``eps_hat = s x_k + a out``. The network still
  predicts the clean plan (as CTG's, trained with a loss on it), preconditioned: the
  skip term ``a x_k`` carries the input at low noise (EDM's ``c_skip`` for unit-variance
  data), and the zero-initialised head starts at ``x0_hat = a x_k``, the exact
  denoiser of standard normal data;
* ``prediction="sample"`` (CTG's tbsim diffuser): ``x0_hat = out``;
* ``prediction="epsilon"`` (Ho et al. 2020): ``eps_hat = out``, ``x0_hat`` from the
  schedule, clipped to ``+-X0_CLIP`` normalised units when sampling.

``x`` is the normalised (accel, yaw rate) plan of every agent, ``(B, A, T, 2)``, as in
RiskFlow, and a diffusion checkpoint is a RiskFlow generator checkpoint whose
``train_config`` says ``generator: "diffusion"`` (``riskflow-train --generator
diffusion``); :func:`load_diffusion` reads one back.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from policies.baselines.diffusion.schedule import SCHEDULES, DiffusionSchedule, ScheduleConfig
from policies.learned.checkpoint import frozen_generator, read_checkpoint
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.encoder import SceneContext
from policies.learned.generator import CheckpointError, RiskFlowGenerator
from policies.learned.window_types import WindowBatch

DEFAULT_NAME = "diffusion_default.pt"
PREDICTIONS = ("v", "sample", "epsilon")
X0_CLIP = 10.0  # bound of an epsilon-model's x0_hat while sampling [normalised units]


@dataclass(frozen=True)
class DiffusionConfig:
    """What makes a generator network a denoiser.

    Attributes:
        num_steps: ``K`` diffusion levels (100, as in CTG).
        schedule: ``"cosine"`` or ``"linear"`` (:class:`ScheduleConfig`).
        prediction: ``"v"``, ``"sample"`` or ``"epsilon"`` (module docstring).
    """

    num_steps: int = 100
    schedule: str = "cosine"
    prediction: str = "v"

    def __post_init__(self) -> None:
        ScheduleConfig(self.num_steps, self.schedule)  # validates both
        if self.prediction not in PREDICTIONS:
            raise ValueError(
                f"DiffusionConfig.prediction must be one of {PREDICTIONS}, got {self.prediction!r}"
            )

    @classmethod
    def from_train_config(cls, train_config: Mapping[str, Any] | None) -> DiffusionConfig:
        """From a checkpoint's ``train_config`` (``riskflow-train --generator diffusion``).

        Raises:
            CheckpointError: the checkpoint is not a diffusion model.
        """
        if not isinstance(train_config, Mapping) or train_config.get("generator") != "diffusion":
            kind = train_config.get("generator") if isinstance(train_config, Mapping) else None
            raise CheckpointError(
                f"not a diffusion checkpoint: train_config['generator'] is {kind!r}, expected "
                "'diffusion' (train one with `riskflow-train --generator diffusion`)"
            )
        try:
            return cls(
                num_steps=int(train_config["diffusion_steps"]),
                schedule=str(train_config["diffusion_schedule"]),
                prediction=str(train_config["diffusion_prediction"]),
            )
        except (KeyError, ValueError) as err:
            raise CheckpointError(f"diffusion checkpoint has invalid settings: {err}") from None


class DiffusionDenoiser:
    """``(x0_hat, eps_hat) = denoise(x_k, k; C)`` on top of a :class:`RiskFlowGenerator`.

    Args:
        network: the generator whose encoder and head are the denoiser.
        diffusion: levels, schedule and parameterisation.
    """

    def __init__(
        self, network: RiskFlowGenerator, diffusion: DiffusionConfig | None = None
    ) -> None:
        self.network = network
        self.diffusion = diffusion or DiffusionConfig()
        self.schedule = DiffusionSchedule(
            ScheduleConfig(self.diffusion.num_steps, self.diffusion.schedule)
        )

    @property
    def config(self) -> ModelConfig:
        """The network's architecture (``future_steps``, ...)."""
        return self.network.config

    def encode(self, batch: WindowBatch) -> SceneContext:
        """Scene context of a batch of windows (once per chain)."""
        return self.network.encode(batch)

    def level_time(self, k: Tensor) -> Tensor:
        """``tau_k = 1 - (k + 1) / K``: the head's time input for level ``k``."""
        return 1.0 - (k + 1.0) / self.diffusion.num_steps

    def __call__(
        self, x_k: Tensor, k: Tensor | int, scene: SceneContext, *, clip: bool = False
    ) -> tuple[Tensor, Tensor]:
        """Clean and noise estimates at level ``k``.

        Args:
            x_k: ``(B, A, T, 2)`` normalised noisy plans.
            k: level, an int or ``(B,)`` ints in ``[0, K)``.
            scene: ``encode(batch)`` of the same ``B`` scenes.
            clip: clip an epsilon-model's ``x0_hat`` to ``+-X0_CLIP`` (sampling).

        Returns:
            ``(x0_hat, eps_hat)``, both ``(B, A, T, 2)``; 0 rows for padded agents.
        """
        k = torch.as_tensor(k, device=x_k.device)
        k = torch.broadcast_to(k, x_k.shape[:1]).to(x_k.dtype)
        tau = self.level_time(k)
        out = self.network.average_velocity(x_k, tau, tau, scene)
        levels = k.long()
        if self.diffusion.prediction == "v":
            scale, std = self.schedule.q_moments(levels, x_k)
            return scale * x_k - std * out, std * x_k + scale * out
        if self.diffusion.prediction == "sample":
            return out, self.schedule.eps_from_x0(x_k, levels, out)
        x0_hat = self.schedule.x0_from_eps(x_k, levels, out)
        if clip:
            x0_hat = x0_hat.clamp(-X0_CLIP, X0_CLIP)
            return x0_hat, self.schedule.eps_from_x0(x_k, levels, x0_hat)
        return x0_hat, out

    def checkpoint_options(self) -> dict[str, Any]:
        """The ``train_config`` entries that :meth:`DiffusionConfig.from_train_config` reads."""
        return {
            "generator": "diffusion",
            "diffusion_steps": self.diffusion.num_steps,
            "diffusion_schedule": self.diffusion.schedule,
            "diffusion_prediction": self.diffusion.prediction,
        }


def load_diffusion(
    path: str | os.PathLike | None = None,
    device: torch.device | str = "cpu",
    config: ModelConfig | None = None,
) -> tuple[DiffusionDenoiser, ActionNormalizer, dict[str, Any]]:
    """Load a diffusion checkpoint: ``(denoiser, normalizer, metadata)``.

    Args:
        path: a checkpoint of ``riskflow-train --generator diffusion``; None loads the
            shipped ``policies/checkpoints/diffusion_default.pt``.
        device: where the network goes (eval mode, no gradients).
        config: optional expected architecture (a mismatch raises, naming the fields).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: the file is not a diffusion checkpoint or does not fit.
    """
    checkpoint = read_checkpoint(
        path,
        DEFAULT_NAME,
        "diffusion",
        "`riskflow-train --generator diffusion` (docs/how-to/baselines.md)",
    )
    diffusion = DiffusionConfig.from_train_config(checkpoint.get("train_config"))
    network, normalizer, metadata = frozen_generator(checkpoint, config, device)
    return DiffusionDenoiser(network, diffusion), normalizer, metadata


__all__ = [
    "DEFAULT_NAME",
    "PREDICTIONS",
    "SCHEDULES",
    "DiffusionConfig",
    "DiffusionDenoiser",
    "load_diffusion",
]
