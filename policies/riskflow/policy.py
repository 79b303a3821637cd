"""``RiskFlowAdversary``: the closed-loop RiskFlow scene policy (docs/explanation/architecture.md).

It drives every non-ego vehicle. Every planning cycle (``planning_interval``, 0.5 s =
5 steps by default) it re-plans from the current :class:`~riskflow_env.view.SceneView`
(receding horizon, as in RiskFlow, Lan et al. 2026):

1. ``encode``: one window (ego frame; docs/how-to/windows.md) and one encoder pass;
2. ``rank``: TTC causal ranking -> the controllable set ``A_c``
   (:mod:`policies.learned.ranking`; from the window's current states, so it comes first:
   the avoidance steps need it); with ``target="ego"`` one moving attacker at a time,
   ahead of or beside a moving ego and kept across cycles (:func:`~policies.learned.
   ranking.ego_attacker`);
3. ``generate``, ``stitch``, ``decode``: one MeanFlow pass for all agents,
   ``u0 = u_theta(eps, 0, 1; C)``, blended into the executed plans, base plans
   ``a = clip(denorm(eps + u0))`` (:mod:`policies.learned.sampler`);
4. ``avoid``, ``stand``: the avoidance steps; done vehicles stand still;
5. ``guide``: output-space guidance of the ``A_c`` rows (:mod:`policies.riskflow.guidance`);
6. ``emit``, ``hold``, ``restitch``: the plans into the plan buffer (world frame),
   vehicles at rest held, the guided rows blended into the executed plans
   (:mod:`policies.pipeline.stages`).

The vehicles outside ``A_c`` follow their base plans, those in ``A_c`` the guided ones;
each env step emits the next action of each plan (plan buffer). Vehicles that are live
but got no window slot (beyond ``WindowConfig.max_distance`` of the ego, or past its
``max_agents``) *hold speed and heading* (zero acceleration and yaw rate) until a cycle
gives them a plan. Done vehicles stay in the window as obstacles standing still (as the
env keeps them): their plan is their current pose at speed 0, and they are never in
``A_c``.

Determinism: the noise ``eps`` of cycle ``c`` of episode ``e`` (``reset`` count from 0)
comes from a ``torch.Generator`` seeded with ``(seed, e, c)``, so the same seed gives the
same closed-loop rollout, bit for bit, on one machine (same device and thread count).
The schedule, plan buffer, seeding and overlays are :class:`~policies.pipeline.policy.
PipelinePolicy`'s, shared with every learned scene policy.

Generator (:mod:`policies.riskflow.base_generator`): the shipped MeanFlow model by
default; ``generator="diffusion"`` (or a diffusion ``checkpoint``) plans with the
diffusion baselines' denoiser run as a deterministic DDIM chain from ``eps`` instead,
with the same ranking and output-space guidance (the generator ablation of issue 7).
``lambda_adv = 0`` / ``lambda_map = 0`` drop a guidance term (the loss ablation).

The realistic base (the defaults): each new base plan is blended into the executed one
over 15 steps (blending first, :mod:`policies.learned.plan_stitching`), then up to 20
avoidance steps pull the MeanFlow base plans' boxes apart and onto the road
(:mod:`policies.learned.plan_avoidance`; the pairs of a vehicle of ``A_c`` and one of its
targets are left to guidance), and vehicles at rest whose new plan moves them less than
4 m keep their brake on; the map term weighs 20. ``avoid_steps=0, hold_distance=0`` is
RiskFlow on the raw generator (``riskflow-eval --methods riskflow-raw``), to report the
model's own traffic next to the rule layer's.

Many scenes: :func:`~policies.pipeline.stages.plan_scenes` plans B scenes in one cycle
(``BatchedAdversary``; ``plan`` is B = 1): the windows are cut and ranked scene by scene
(numpy, a loop over scenes), everything else runs once for all of them, agents padded to
the largest scene and masked; scene ``b`` draws its noise from its own stream.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import torch

from policies.learned.adversary_config import AdversaryConfig, default_window_config
from policies.learned.data import Normalizer
from policies.learned.generator import RiskFlowGenerator
from policies.pipeline import stages
from policies.pipeline.policy import BASE_COLOR, GUIDED_COLOR, PipelinePolicy, Stage
from policies.riskflow.base_generator import resolve_avoid_steps, resolve_generator
from policies.riskflow.guidance import GuidanceConfig, guide_outputs
from riskflow_env.config import plain_number

if TYPE_CHECKING:
    from policies.baselines.diffusion.sampling import OneCallSampler

PHASES = ("window", "encoder", "generator", "ranking", "guidance")


def generator_stages(avoid_steps: int, hold_distance: float, guide: Stage | None) -> tuple:
    """The cycle of a policy on the one-step generator: the avoidance steps and holding
    at rest only when on (``avoid_steps > 0``, ``hold_distance > 0``; the avoidance steps
    decode the plans they return, so ``decode`` runs only without them), the ranking and
    ``guide`` only with a guidance stage."""
    guided = guide is not None
    return tuple(
        stage
        for stage, on in (
            (stages.encode, True),
            (stages.rank, guided),
            (stages.generate, True),
            (stages.stitch, True),
            (stages.decode, avoid_steps == 0),  # the avoidance steps decode their result
            (stages.avoid, avoid_steps > 0),
            (stages.stand, True),
            (guide, guided),
            (stages.emit, True),
            (stages.hold, hold_distance > 0),
            (stages.restitch, True),
        )
        if on
    )


class GeneratorPolicy(PipelinePolicy):
    """A pipeline policy on the one-step base generator: what RiskFlow, the unguided
    generator and STRIVE-style share (the generator, its avoidance steps and the cycle of
    :func:`generator_stages` with the method's ``guide`` stage, or none).

    Args:
        config: the shared options.
        guidance: the guidance objective and optimiser (its map term also scores the
            avoidance steps' off-road depth).
        guide_stage: the method's ``guide`` stage; None: unguided.
        generator, normalizer, checkpoint, sampling_steps: the base generator
            (:func:`~policies.riskflow.base_generator.resolve_generator`).
        avoid_steps, avoid_step_size: the avoidance steps
            (:func:`~policies.riskflow.base_generator.resolve_avoid_steps`).
    """

    def __init__(
        self,
        config: AdversaryConfig,
        guidance: GuidanceConfig,
        guide_stage: Stage | None,
        generator: object,
        normalizer: Normalizer | None,
        checkpoint: str | os.PathLike | None,
        sampling_steps: int | None,
        avoid_steps: int | None,
        avoid_step_size: float,
        /,
    ) -> None:
        self.guidance = guidance
        self.model, self.normalizer, self.generator_kind = resolve_generator(
            generator, normalizer, checkpoint, sampling_steps, torch.device(config.device)
        )
        self.avoid_steps = resolve_avoid_steps(avoid_steps, avoid_step_size, self.generator_kind)
        self.avoid_step_size = float(plain_number(avoid_step_size))
        model_config = self.model.config
        super().__init__(
            config,
            model_config.future_steps,
            config.window_config or default_window_config(model_config),
            generator_stages(self.avoid_steps, config.hold_distance, guide_stage),
            self.model.encode,
        )


class RiskFlowAdversary(GeneratorPolicy):
    """RiskFlow adversary for every non-ego vehicle (module docstring).

    Args:
        config: the options every learned adversary shares
            (:class:`~policies.learned.adversary_config.AdversaryConfig`: ``k``,
            ``planning_interval``, ``target``, ``lambda_adv``, ``lambda_map``,
            ``guidance_horizon``, ``rank_threshold``, ``seed``,
            ``device``, ``window_config``, ``threads``); or give them as keywords
            (``**options``).
        guidance_steps: ``K_g``.
        step_size: Adam learning rate, or ``gamma`` of plain steps; None (default): 0.01
            with target ``"others"``, 0.1 with ``"ego"`` (:class:`GuidanceConfig`).
        optimizer: ``"adam"`` (default) or ``"gradient"`` (the paper's plain steps)
            (:class:`~policies.riskflow.guidance.GuidanceConfig`).
        lambda_sep: weight of the separation of the guided vehicles from each other
            (:class:`GuidanceConfig`; default 100; 0: off, the paper's objective).
        generator: the base-plan generator: a model object (a ``RiskFlowGenerator``, or
            a diffusion ``OneCallSampler``; moved to ``device``, eval mode) with its
            ``normalizer``; or ``"meanflow"`` / ``"diffusion"`` to load that kind from
            ``checkpoint`` (default: the shipped file of that kind); None: the kind of
            ``checkpoint``, MeanFlow without one (:mod:`policies.riskflow.base_generator`).
        normalizer: the model's action normalisation (required with a model object).
        checkpoint: a ``riskflow-train`` checkpoint file to load (its kind is read from
            it); not with a model object.
        sampling_steps: DDIM levels of a diffusion generator (None: 10); MeanFlow: None.
        avoid_steps: Adam steps that pull the base plans apart and onto the road before
            ranking (:mod:`policies.learned.plan_avoidance`); None (default):
            ``DEFAULT_AVOID_STEPS`` (20) with the MeanFlow generator, 0 with a diffusion
            one (which has none); 0: off.
        avoid_step_size: their Adam learning rate (normalised action units).
        **options: :class:`AdversaryConfig` fields, when ``config`` is not given.
    """

    phases = PHASES

    def __init__(
        self,
        config: AdversaryConfig | None = None,
        *,
        guidance_steps: int = 30,
        step_size: float | None = GuidanceConfig.step_size,
        optimizer: str = GuidanceConfig.optimizer,
        lambda_sep: float = GuidanceConfig.lambda_sep,
        generator: RiskFlowGenerator | OneCallSampler | str | None = None,
        normalizer: Normalizer | None = None,
        checkpoint: str | os.PathLike | None = None,
        sampling_steps: int | None = None,
        avoid_steps: int | None = None,
        avoid_step_size: float = 0.1,
        **options: Any,
    ) -> None:
        config = AdversaryConfig.resolve(config, options, type(self).__name__)
        guidance = GuidanceConfig.of(config, guidance_steps, step_size, optimizer, lambda_sep)
        super().__init__(
            config, guidance, guide_outputs, generator, normalizer, checkpoint, sampling_steps,
            avoid_steps, avoid_step_size,
        )  # fmt: skip


__all__ = [
    "BASE_COLOR",
    "GUIDED_COLOR",
    "PHASES",
    "GeneratorPolicy",
    "RiskFlowAdversary",
    "generator_stages",
]
