"""``riskflow-train --generator diffusion``: the diffusion denoiser's training objective.

There is one training loop (``policies.learned.trainer.fit``: batches, Adam, gradient
clipping, EMA, validation, checkpoints, resume); this module is the objective it plugs in
for ``--generator diffusion``: per step, levels ``k ~ U{0..K-1}`` after the loop's noise
``eps``, from the run's seeded noise generator (so ``--resume`` stays exact) and
:func:`~policies.baselines.diffusion.objective.diffusion_loss`. Validation samples the
EMA denoiser with deterministic DDIM (``--val-sampling-steps`` levels) through
:class:`~policies.baselines.diffusion.sampling.OneCallSampler`, so the validation
numbers (ADE, minADE, jerk, ...) are those of the MeanFlow runs, measured alike::

    riskflow-train --generator diffusion --data data/train --val-data data/val \\
        --out runs/diffusion --lr 5e-4

The checkpoint is a generator checkpoint whose ``train_config`` carries ``generator``,
``diffusion_steps``, ``diffusion_schedule`` and ``diffusion_prediction``
(:func:`~policies.baselines.diffusion.model.load_diffusion` reads them).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from policies.baselines.diffusion.model import DiffusionConfig, DiffusionDenoiser
from policies.baselines.diffusion.objective import diffusion_loss, draw_levels
from policies.baselines.diffusion.sampling import OneCallSampler
from policies.learned.data import Normalizer
from policies.learned.distributed import Shard
from policies.learned.generator import RiskFlowGenerator
from policies.learned.trajectory_loss import LossWeights
from policies.learned.window_types import WindowBatch


class DiffusionObjective:
    """The ``--generator diffusion`` objective of ``riskflow-train``.

    Args:
        diffusion: levels, schedule, parameterisation.
        val_sampling_steps: DDIM levels of the validation samples.
    """

    kind = "diffusion"

    def __init__(self, diffusion: DiffusionConfig, val_sampling_steps: int = 10) -> None:
        self.diffusion = diffusion
        self.val_sampling_steps = min(val_sampling_steps, diffusion.num_steps)

    @classmethod
    def from_options(cls, options: Any) -> DiffusionObjective:
        """From ``riskflow-train``'s ``TrainOptions`` (its ``diffusion_*`` fields)."""
        diffusion = DiffusionConfig(
            num_steps=options.diffusion_steps,
            schedule=options.diffusion_schedule,
            prediction=options.diffusion_prediction,
        )
        return cls(diffusion, options.val_sampling_steps)

    def denoiser(self, model: RiskFlowGenerator) -> DiffusionDenoiser:
        """``model`` seen as the denoiser."""
        return DiffusionDenoiser(model, self.diffusion)

    def loss(
        self,
        model: RiskFlowGenerator,
        batch: WindowBatch,
        normalizer: Normalizer,
        eps: Tensor,
        generator: torch.Generator,
        weights: LossWeights,
        shard: Shard,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """One step's loss and metrics (``weights`` as :func:`diffusion_loss`); the levels
        are drawn for ``shard``'s whole global batch and its rows taken."""
        k = draw_levels(shard.total, self.diffusion.num_steps, generator, eps.device)
        k = shard.rows(k)
        return diffusion_loss(self.denoiser(model), batch, normalizer, eps, k, weights)

    def sampler(self, model: RiskFlowGenerator) -> OneCallSampler:
        """What validation samples: deterministic DDIM with ``val_sampling_steps`` levels."""
        return OneCallSampler(self.denoiser(model), self.val_sampling_steps)


__all__ = ["DiffusionObjective"]
