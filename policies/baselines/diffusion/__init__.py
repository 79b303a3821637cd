"""Guided-diffusion baselines: CTG-, CTG++- and CCDiff-style adversaries (docs/how-to/baselines.md).

One action-space DDPM (RiskFlow's encoder and head as the denoiser, ``model.py``;
schedule and DDIM in ``schedule.py``; trained by ``riskflow-train --generator
diffusion``, ``train.py`` / ``objective.py``), sampled by ``sampling.py``, guided with
RiskFlow's own losses by ``guided.py``, driven closed-loop by ``policy.py``.
"""

from __future__ import annotations

from policies.baselines.diffusion.guided import (
    DiffusionGuidanceConfig,
    GuidedPlans,
    SceneGeometry,
    guided_sample,
)
from policies.baselines.diffusion.model import (
    DiffusionConfig,
    DiffusionDenoiser,
    load_diffusion,
)
from policies.baselines.diffusion.objective import diffusion_loss
from policies.baselines.diffusion.policy import VARIANTS, DiffusionAdversary
from policies.baselines.diffusion.sampling import OneCallSampler, chain_noise, reverse_chain
from policies.baselines.diffusion.schedule import DiffusionSchedule, ScheduleConfig

__all__ = [
    "VARIANTS",
    "DiffusionAdversary",
    "DiffusionConfig",
    "DiffusionDenoiser",
    "DiffusionGuidanceConfig",
    "DiffusionSchedule",
    "GuidedPlans",
    "OneCallSampler",
    "SceneGeometry",
    "ScheduleConfig",
    "chain_noise",
    "diffusion_loss",
    "guided_sample",
    "load_diffusion",
    "reverse_chain",
]
