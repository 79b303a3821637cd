"""``DiffusionAdversary``: the CTG-, CTG++- and CCDiff-style scene policies.

The same closed-loop machinery as ``RiskFlowAdversary``
(:class:`~policies.pipeline.policy.PipelinePolicy`: re-plan every ``planning_interval``,
plan buffer, seeded noise per (seed, episode, cycle), done vehicles standing still,
world-frame plans, overlays); its planning cycle is the stages

1. ``encode``: one window, one encoder pass (the scene context);
2. ``select``: the controllable set ``A_c``: the ``k`` live vehicles nearest the ego
   (``"ctg"``, ``"ctgpp"``) or the TTC causal ranking (``"ccdiff"``;
   :mod:`policies.learned.ranking`);
3. ``chain``: the unguided reverse chain (DDPM with all ``K`` levels, or DDIM with
   ``sampling_steps``), then the guided chain of ``A_c`` (:mod:`.guided`): gradient of
   RiskFlow's ``L_adv + L_map`` on the transition mean (``"ctg"``, ``"ccdiff"``) or
   through the predicted clean sample (``"ctgpp"``), at every level;
4. ``emit``, ``hold``, ``restitch``: the plans into the plan buffer, vehicles at rest
   held, every new plan blended into the executed one (over 5 steps).

Several scenes due to re-plan in one call (:class:`~policies.pipeline.batched.
BatchedAdversary`, ``riskflow-eval --batch-scenes``) share one encoder pass and one
denoiser pass per level of each chain, agents padded per scene and masked; each scene
gets the plans it gets alone, to float rounding.

All the cycle's noise (chain start and every transition; kept in ``noise``, shape
``(levels + 1, A_window, T, 2)``) is drawn from the seeded generator, so the same seed
gives the same rollout; ``k = 0`` gives the unguided
diffusion generator. Method mapping and simplifications: ``docs/how-to/baselines.md``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from policies.baselines.diffusion.guided import (
    DiffusionGuidanceConfig,
    SceneGeometry,
    guided_sample,
)
from policies.baselines.diffusion.model import DiffusionDenoiser, load_diffusion
from policies.baselines.diffusion.sampling import chain_noise
from policies.learned.adversary_config import (
    AdversaryConfig,
    check_model_pair,
    default_window_config,
)
from policies.learned.data import Normalizer
from policies.learned.ranking import NO_GROUP, Ranking, rank_window
from policies.learned.window_types import Window
from policies.pipeline import stages
from policies.pipeline.plan_set import PlanSet
from policies.pipeline.policy import PipelinePolicy

PHASES = ("window", "encoder", "ranking", "denoising", "guidance")
# variant -> (A_c selection, guidance gradient)
VARIANTS = {"ctg": ("nearest", "mean"), "ctgpp": ("nearest", "clean"), "ccdiff": ("causal", "mean")}


def nearest_ranking(window: Window, k: int | str, candidates: np.ndarray) -> Ranking:
    """``A_c`` = the ``k`` candidates nearest the ego (slot 0) at the current step.

    Ties go to the lower slot. ``scores`` are minus the distances [m]; no groups.
    """
    current = np.asarray(window.history)[:, -1, :2]
    distance = np.linalg.norm(current - current[0], axis=-1)
    candidates = np.asarray(candidates, dtype=bool) & np.asarray(window.agent_mask, bool)
    candidates[0] = False
    slots = np.flatnonzero(candidates)
    order = slots[np.lexsort((slots, distance[slots]))]
    count = order.size if k == "all" else min(int(k), order.size)
    controllable = np.zeros(distance.shape[0], dtype=bool)
    controllable[order[:count]] = True
    groups = np.full(distance.shape[0], NO_GROUP, dtype=np.int64)
    return Ranking(controllable, -distance, groups, order)


class DiffusionAdversary(PipelinePolicy):
    """A guided diffusion adversary for every non-ego vehicle (module docstring).

    Args:
        config: the options every learned adversary shares
            (:class:`~policies.learned.adversary_config.AdversaryConfig`: ``k``,
            ``planning_interval``, ``target``, ``lambda_adv``, ``lambda_map``,
            ``guidance_horizon``, ``rank_threshold`` (``"ccdiff"``),
            ``seed``, ``device``, ``window_config``, ``threads``); or give them as keywords
            (``**options``).
        variant: ``"ctg"``, ``"ctgpp"`` or ``"ccdiff"``.
        sampling_steps: levels of the chain: None for all ``K`` (DDPM), fewer for DDIM.
        eta: DDIM stochasticity (1: DDPM-like ancestral noise; 0: deterministic).
        step_size: per-agent RMS of one guidance step [normalised action units].
        lambda_sep: weight of the separation of the guided vehicles from each other
            (:class:`~policies.learned.guidance_losses.ObjectiveConfig`; default 100, as
            RiskFlow's and STRIVE-style's; 0: off, the original methods' objective).
        inner_steps: guidance steps per level (``"ctg"``, ``"ccdiff"``).
        anchor: the vehicles outside ``A_c`` follow the unguided chain, bit for bit (two
            chains per cycle); False: one chain, they are denoised jointly with ``A_c``
            (:mod:`.guided`).
        denoiser: the model; None loads ``policies/checkpoints/diffusion_default.pt``.
        normalizer: its action normalisation (required with ``denoiser``).
        **options: :class:`AdversaryConfig` fields, when ``config`` is not given.
    """

    overlay_prefix = "diffusion"
    phases = PHASES

    def __init__(
        self,
        config: AdversaryConfig | None = None,
        *,
        variant: str = "ctg",
        sampling_steps: int | None = None,
        eta: float = 1.0,
        step_size: float = DiffusionGuidanceConfig.step_size,
        lambda_sep: float = DiffusionGuidanceConfig.lambda_sep,
        inner_steps: int = 1,
        anchor: bool = True,
        denoiser: DiffusionDenoiser | None = None,
        normalizer: Normalizer | None = None,
        **options: Any,
    ) -> None:
        config = AdversaryConfig.resolve(config, options, type(self).__name__)
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {tuple(VARIANTS)}, got {variant!r}")
        if not 0.0 <= eta <= 1.0:
            raise ValueError(f"eta must be in [0, 1], got {eta}")
        self.variant, self.eta = variant, float(eta)
        self.selection, gradient = VARIANTS[variant]
        self.guidance = DiffusionGuidanceConfig(
            gradient=gradient,
            inner_steps=inner_steps,
            step_size=step_size,
            lambda_sep=lambda_sep,
            anchor=anchor,
            **config.objective(),
        )
        device = torch.device(config.device)
        check_model_pair(denoiser, normalizer, "denoiser")
        if denoiser is None:
            denoiser, normalizer, _ = load_diffusion(None, device=device)
        denoiser.network.to(device).eval()
        self.denoiser, self.normalizer = denoiser, normalizer
        self.levels = denoiser.schedule.levels(sampling_steps)
        model_config = denoiser.config
        window_config = config.window_config or default_window_config(model_config)
        cycle = [stages.encode, select, chain, stages.emit]
        cycle += [stages.hold] * (config.hold_distance > 0) + [stages.restitch]
        super().__init__(config, model_config.future_steps, window_config, cycle, denoiser.encode)


def select(policy: DiffusionAdversary, plans: PlanSet) -> PlanSet:
    """``A_c`` of each scene: the ``k`` live vehicles nearest the ego, or the TTC causal
    ranking (``"ccdiff"``); numpy, scene by scene."""
    observed = plans.observed
    controllable = np.zeros(observed.scene.agent_mask.shape, dtype=bool)
    rankings = []
    for index, view in enumerate(plans.views):
        window, slots = observed.windows[index], observed.slots[index]
        live = view.active[slots]
        if policy.selection == "causal":
            ranking = rank_window(window, policy.k, policy.rank_threshold, live)
        else:
            ranking = nearest_ranking(window, policy.k, live)
        controllable[index, : len(slots)] = ranking.controllable
        rankings.append(ranking)
    controllable = torch.from_numpy(controllable).to(policy.device)
    return plans.replace(controllable=controllable, rankings=rankings)


select.phase = "ranking"


def chain(policy: DiffusionAdversary, plans: PlanSet) -> PlanSet:
    """One base chain and one guided chain for all scenes (module docstring). Each scene
    draws its noise from its own stream, with the shape it has alone; the padded rows of
    smaller scenes are masked everywhere."""
    observed = plans.observed
    scene, counts = observed.scene, observed.counts
    num_scenes, num_agents = scene.agent_mask.shape
    standing = np.zeros((num_scenes, num_agents), dtype=bool)
    for index, (view, slots) in enumerate(zip(plans.views, observed.slots, strict=True)):
        standing[index, : len(slots)] = ~view.active[slots]
    steps = policy.horizon
    noise = scene.context.new_zeros(len(policy.levels) + 1, num_scenes, num_agents, steps, 2)
    for index, (state, count) in enumerate(zip(plans.states, counts, strict=True)):
        noise[:, index, :count] = chain_noise(  # the scene's own stream, its own shape
            (1, count, steps, 2), policy.levels, state.noise_source(policy.device),
            policy.device, scene.context.dtype,
        )[:, 0]  # fmt: skip
    geometry = SceneGeometry(
        state=scene.state,
        length=observed.batch.length,
        width=observed.batch.width,
        agent_mask=scene.agent_mask,
        drivable_map=plans.drivable_map,
        frame=observed.frame_tensor(),
        standing=torch.from_numpy(standing).to(policy.device),
    )
    marks = [time.perf_counter()]
    result = guided_sample(
        policy.denoiser, scene, noise, policy.levels, geometry, plans.controllable,
        policy.normalizer, policy.guidance, policy.eta, policy.dynamics,
        on_base_done=lambda: marks.append(policy.clock.tick("denoising", marks[0])),
    )  # fmt: skip
    policy.clock.tick("guidance", marks[-1])
    # (levels + 1, A_w, T, 2) per scene: chain start, then each transition
    kept = [noise[:, index, :count] for index, count in enumerate(counts)]
    return plans.replace(
        base_actions=result.base_actions, base_trajectories=result.base_trajectories,
        actions=result.actions, trajectories=result.trajectories, losses=result.losses,
        noise=kept,
    )  # fmt: skip


__all__ = ["PHASES", "VARIANTS", "DiffusionAdversary", "chain", "nearest_ranking", "select"]
