"""``RiskFlowAdversary``: the closed-loop RiskFlow scene policy (docs/ARCHITECTURE.md).

It drives every non-ego vehicle. Every planning cycle (``planning_interval``, 0.5 s =
5 steps by default) it re-plans from the current :class:`~riskflow_env.view.SceneView`
(receding horizon, as in RiskFlow, Lan et al. 2026):

1. ``window_from_view`` -> one window (ego frame; docs/WINDOWS.md);
2. TTC causal ranking -> the controllable set ``A_c`` (:mod:`policies.learned.ranking`;
   from the window's current states, so it comes first: the avoidance steps need it);
3. one encoder pass and one MeanFlow pass for all agents: ``u0 = u_theta(eps, 0, 1; C)``,
   base plans ``a = clip(denorm(eps + u0))`` (:mod:`policies.learned.sampler`);
4. output-space guidance of the ``A_c`` rows (:mod:`policies.riskflow.guidance`).

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
The schedule, plan buffer, seeding and overlays are :class:`~policies.learned.plan_buffer.
PlanBufferPolicy`'s, shared with the diffusion baselines.

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

Many scenes: ``_plan_cycles`` plans B scenes in one call (``plan_scenes``,
``BatchedAdversary``; ``plan`` is B = 1): the windows are cut and ranked scene by scene
(numpy, a loop over scenes), everything else runs once for all of them, agents padded to
the largest scene and masked; scene ``b`` draws its noise from its own stream.

Subclasses replace how ``A_c`` is optimised by overriding :meth:`RiskFlowAdversary._guide`
(the STRIVE-style baseline optimises the generator's input noise instead).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from policies.learned.adversary_config import (
    AdversaryConfig,
    check_model_pair,
    default_window_config,
)
from policies.learned.data import Normalizer
from policies.learned.encoded_views import EncodedViews
from policies.learned.generator import RiskFlowGenerator
from policies.learned.plan_avoidance import DEFAULT_AVOID_STEPS
from policies.learned.plan_buffer import PlanBufferPolicy, hold_still
from policies.learned.plan_overlay import BASE_COLOR, GUIDED_COLOR
from policies.learned.ranking import rank_window
from policies.learned.sampler import base_velocity
from policies.riskflow.base_generator import generator_kind, load_base_generator
from policies.riskflow.base_plans import BasePlanSteps
from policies.riskflow.guidance import (
    GuidanceConfig,
    GuidanceResult,
    GuidanceScene,
    guide,
    plans_from_velocity,
)
from riskflow_env.view import SceneView

if TYPE_CHECKING:
    from policies.baselines.diffusion.sampling import OneCallSampler

PHASES = ("window", "encoder", "generator", "ranking", "guidance")


class RiskFlowAdversary(BasePlanSteps, PlanBufferPolicy):
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
        if avoid_steps is not None and (
            isinstance(avoid_steps, bool) or not isinstance(avoid_steps, int) or avoid_steps < 0
        ):
            raise ValueError(f"avoid_steps must be None or an int >= 0, got {avoid_steps!r}")
        if isinstance(avoid_step_size, bool) or not (
            isinstance(avoid_step_size, (int, float)) and 0 < avoid_step_size < float("inf")
        ):
            raise ValueError(
                f"avoid_step_size must be a finite number > 0, got {avoid_step_size!r}"
            )
        self.stitch_first = True
        self.avoid_step_size = float(avoid_step_size)
        self.guidance = GuidanceConfig(
            steps=guidance_steps,
            step_size=step_size,
            optimizer=optimizer,
            lambda_sep=lambda_sep,
            **config.objective(),
        )
        device = torch.device(config.device)
        if generator is None or isinstance(generator, str):
            check_model_pair(None, normalizer, "generator")
            generator, normalizer, self.generator_kind = load_base_generator(
                generator, checkpoint, device, sampling_steps
            )
        else:
            check_model_pair(generator, normalizer, "generator")
            if checkpoint is not None or sampling_steps is not None:
                raise ValueError(
                    "checkpoint and sampling_steps go with generator=None or a kind name, "
                    "not with a model object"
                )
            self.generator_kind = generator_kind(generator)
        if avoid_steps is None:
            avoid_steps = DEFAULT_AVOID_STEPS if self.generator_kind == "meanflow" else 0
        if avoid_steps > 0 and self.generator_kind != "meanflow":
            raise ValueError(
                f"avoid_steps > 0 needs the MeanFlow generator, got {self.generator_kind!r}"
            )
        self.avoid_steps = avoid_steps
        self.model = generator.to(device).eval()
        self.normalizer = normalizer
        model_config = self.model.config
        window_config = config.window_config or default_window_config(model_config)
        super().__init__(config, model_config.future_steps, window_config)

    def _plan_cycles(self, scenes: Sequence[PlanBufferPolicy], views: Sequence[SceneView]) -> None:
        """One cycle of B scenes (``scenes[b]`` plans ``views[b]``; B = 1 for ``plan``):
        windows and one encoder pass, ranking, one MeanFlow pass, one guidance loop (module
        docstring). Each scene draws its noise from its own stream, with the shape it has
        alone, and the padded rows of smaller scenes are masked everywhere."""
        observed = self._encode_views(views, self.model.encode)
        scene, counts = observed.scene, observed.counts
        num_scenes, num_agents = scene.agent_mask.shape
        controllable = np.zeros((num_scenes, num_agents), dtype=bool)
        for index, (policy, view) in enumerate(zip(scenes, views, strict=True)):
            window, slots = observed.windows[index], observed.slots[index]
            policy.ranking = rank_window(window, self.k, self.rank_threshold, view.active[slots])
            controllable[index, : len(slots)] = policy.ranking.controllable
        controllable = torch.from_numpy(controllable).to(self.device)
        clock = self._tick("ranking", observed.clock)
        steps = self.model.config.future_steps
        with torch.no_grad():
            eps = scene.context.new_zeros(num_scenes, num_agents, steps, 2)
            for index, (policy, count) in enumerate(zip(scenes, counts, strict=True)):
                eps[index, :count] = torch.randn(  # the scene's own stream, its own shape
                    (count, steps, 2),
                    generator=policy._noise_source(),
                    device=self.device,
                    dtype=scene.context.dtype,
                )
            u0 = base_velocity(self.model, eps, scene)
            gain = None
            if self.stitch_first:
                u0, gain = self._blend_first(scenes, views, observed.slots, eps, u0)
            actions, trajectories = plans_from_velocity(
                eps, u0, scene.state, scene.agent_mask, self.normalizer, self.dynamics
            )
            if self.avoid_steps > 0:
                u0, actions, trajectories = self._avoid(
                    observed, views, eps, u0, gain, controllable
                )
            done = np.zeros((num_scenes, num_agents), dtype=bool)
            for index, (view, slots) in enumerate(zip(views, observed.slots, strict=True)):
                done[index, : len(slots)] = ~view.active[slots]
            done = torch.from_numpy(done).to(self.device)
            hold_still(actions, trajectories, scene.state, done)  # the env keeps them at speed 0
        clock = self._tick("generator", clock)
        guidance_scene = GuidanceScene(
            eps=eps,
            u0=u0,
            state=scene.state,
            length=observed.batch.length,
            width=observed.batch.width,
            agent_mask=scene.agent_mask,
            base_actions=actions,
            base_trajectories=trajectories,
            drivable_map=self._map_of(views),
            frame=observed.frame_tensor(),
        )
        result = self._guide(guidance_scene, controllable, observed)
        self._tick("guidance", clock)
        losses = result.losses.cpu().numpy()
        for index, (policy, view) in enumerate(zip(scenes, views, strict=True)):
            slots = observed.slots[index]
            rows = slice(0, len(slots))
            policy.noise = eps[index, rows]
            policy._store(
                view, slots, result.actions[index, rows], result.trajectories[index, rows],
                trajectories[index, rows], observed.frames[index],
            )  # fmt: skip
            policy.guidance_losses = losses[:, index]

    def _guide(
        self, scene: GuidanceScene, controllable: torch.Tensor, observed: EncodedViews
    ) -> GuidanceResult:
        """Optimise the ``A_c`` rows (``controllable`` (B, A) bool) of the base plans of the
        B scenes in ``scene``: output-space guidance, one loop for all
        (:func:`policies.riskflow.guidance.guide`). ``observed`` has the scene context,
        for methods that re-run the generator."""
        return guide(scene, controllable, self.normalizer, self.guidance, self.dynamics)


__all__ = ["BASE_COLOR", "GUIDED_COLOR", "PHASES", "RiskFlowAdversary"]
