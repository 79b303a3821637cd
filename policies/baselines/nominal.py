"""``NominalGenerator``: the unguided learned generator (BITS-like nominal traffic).

BITS (Xu et al. 2023, "BITS: Bi-level Imitation for Traffic Simulation", ICRA) drives
every agent with a policy imitated from logged traffic, without any adversarial
objective: the *nominal* learned traffic the guided methods are compared against. Here
that role is played by RiskFlow's own learned generator with no guidance: it is
:class:`~policies.riskflow.policy.RiskFlowAdversary` with ``k = 0`` (no controllable
set, so no guidance step runs and every vehicle follows its base plan ``clip(denorm(eps +
u_theta(eps, 0, 1; C)))``, bit for bit the plans of ``RiskFlowAdversary(k=0)`` with the
same seed), re-planned every ``planning_interval`` from the current scene. Its cycle is
RiskFlow's without the ``rank`` and ``guide`` stages
(:func:`~policies.riskflow.policy.generator_stages`). The same
class with ``generator="diffusion"`` is the unguided diffusion generator (deterministic
DDIM from ``eps``).

**Mapping to BITS, and what is simplified**

==========================================  ===========================================
BITS                                        here
==========================================  ===========================================
bi-level policy: a high-level goal          one scene-level generator, no explicit goal:
(spatial intent) predictor, then a          the MeanFlow head maps noise to every
goal-conditioned low-level trajectory       agent's 5.2 s action plan in one pass
policy
prediction-and-planning module: samples     one joint sample per cycle, then avoidance
several goals, predicts the others, picks   steps on a rule-based overlap + off-road
the plan with the best rule-based score     score (:mod:`policies.learned.plan_avoidance`)
per-agent rasterised (BEV) context          vector histories + map crops, social
                                            attention between agents
trained on nuScenes / Lyft Level 5          trained on the shipped highway-env bank
closed loop, re-planning                    closed loop, re-planning every 0.5 s
==========================================  ===========================================
"""

from __future__ import annotations

import os

import torch

from policies.learned.adversary_config import AdversaryConfig
from policies.learned.data import Normalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.windows import WindowConfig
from policies.riskflow.guidance import GuidanceConfig
from policies.riskflow.policy import GeneratorPolicy


class NominalGenerator(GeneratorPolicy):
    """The unguided generator for every non-ego vehicle (module docstring).

    Args:
        planning_interval: time between re-plans [s] (a multiple of ``dt``).
        seed: noise seed.
        device: torch device.
        generator: a model object (with ``normalizer``), ``"meanflow"`` or
            ``"diffusion"`` (the shipped checkpoint of that kind), or None (MeanFlow, or
            ``checkpoint``'s kind); as ``RiskFlowAdversary``.
        normalizer: the model's action normalisation (required with a model object).
        checkpoint: a ``riskflow-train`` checkpoint file.
        sampling_steps: DDIM levels of a diffusion generator (None: 10).
        window_config: window options (default: the model's training windows).
        threads: torch CPU threads while planning; None keeps torch's setting.
        hold_distance: [m] vehicles at rest whose plan moves them less than this keep
            their brake on (``AdversaryConfig.hold_distance``, default 4); 0: off.
        stitch_steps: [steps] a new plan's first actions blended with the executed plan
            (``AdversaryConfig.stitch_steps``; None: 15 blending first, 5 after); 0:
            switch at once.
        avoid_steps, avoid_step_size: Adam steps (None: 20 with the MeanFlow generator,
            0 with a diffusion one; 0: off) and their size that pull the base plans' boxes
            apart and onto the road (``RiskFlowAdversary``,
            :mod:`policies.learned.plan_avoidance`).

    The defaults are the realistic base; ``avoid_steps=0, hold_distance=0`` is the raw
    generator (``riskflow-eval --methods bits-raw``).
    """

    overlay_prefix = "nominal"

    def __init__(
        self,
        planning_interval: float = 0.5,
        seed: int = 0,
        device: torch.device | str = "cpu",
        generator: RiskFlowGenerator | str | None = None,
        normalizer: Normalizer | None = None,
        checkpoint: str | os.PathLike | None = None,
        sampling_steps: int | None = None,
        window_config: WindowConfig | None = None,
        threads: int | None = 1,
        hold_distance: float = AdversaryConfig.hold_distance,
        stitch_steps: int | None = AdversaryConfig.stitch_steps,
        avoid_steps: int | None = None,
        avoid_step_size: float = 0.1,
    ) -> None:
        config = AdversaryConfig(
            k=0, planning_interval=planning_interval, seed=seed, device=device,
            window_config=window_config, threads=threads, hold_distance=hold_distance,
            stitch_steps=stitch_steps,
        )  # fmt: skip
        super().__init__(
            config, GuidanceConfig(steps=0, **config.objective()), None, generator, normalizer,
            checkpoint, sampling_steps, avoid_steps, avoid_step_size,
        )  # fmt: skip


__all__ = ["NominalGenerator"]
