"""``RiskFlowAdversary``: the closed-loop RiskFlow scene policy (DESIGN.md section 3).

It drives every non-ego vehicle. Every planning cycle (``planning_interval``, 0.5 s =
5 steps by default) it re-plans from the current :class:`~riskflow_env.view.SceneView`
(receding horizon, as in RiskFlow, Lan et al. 2026):

1. ``window_from_view`` -> one window (ego frame; docs/WINDOWS.md);
2. one encoder pass and one MeanFlow pass for all agents: ``u0 = u_theta(eps, 0, 1; C)``,
   base plans ``a = clip(denorm(eps + u0))`` (:mod:`policies.riskflow.sampler`);
3. TTC causal ranking -> the controllable set ``A_c`` (:mod:`policies.riskflow.ranking`);
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
The schedule, plan buffer, seeding and overlays are :class:`~policies.riskflow.plan_buffer.
PlanBufferPolicy`'s, shared with the diffusion baselines.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from policies.riskflow.data import collate_windows
from policies.riskflow.encoder import ENCODER_KEYS
from policies.riskflow.generator import RiskFlowGenerator
from policies.riskflow.guidance import (
    GuidanceConfig,
    GuidanceScene,
    guide,
    plans_from_velocity,
)
from policies.riskflow.meanflow import Normalizer
from policies.riskflow.plan_buffer import BASE_COLOR, GUIDED_COLOR, PlanBufferPolicy, hold_still
from policies.riskflow.ranking import DEFAULT_THRESHOLD, rank_window
from policies.riskflow.sampler import base_velocity
from riskflow_env.scenarios.windows import WindowConfig, window_from_view
from riskflow_env.view import SceneView

PHASES = ("window", "encoder", "generator", "ranking", "guidance")


class RiskFlowAdversary(PlanBufferPolicy):
    """RiskFlow adversary for every non-ego vehicle (module docstring).

    Args:
        k: size of ``A_c`` (int >= 0) or ``"all"``; 0 gives the unguided generator.
        planning_interval: time between re-plans [s]; a multiple of the env's ``dt``
            between ``dt`` and the plan horizon.
        target: ``"others"`` (paper: pull toward any non-controllable agent) or ``"ego"``.
        guidance_steps: ``K_g``.
        lambda_adv: adversarial weight; > 0 is more adversarial (``guidance.py``).
        lambda_map: off-road weight, >= 0.
        guidance_horizon: ``T_g`` [steps] of the adversarial term; None: whole plan.
        step_size: Adam learning rate, or ``gamma`` of plain steps (:class:`GuidanceConfig`).
        optimizer: ``"adam"`` (default) or ``"gradient"`` (the paper's plain steps).
        rank_threshold: risk-graph edge threshold.
        seed: noise seed.
        device: torch device of the model.
        generator: the model; None loads the shipped checkpoint
            (``policies.riskflow.checkpoint.load_generator``). It is moved to ``device``
            and put in eval mode.
        normalizer: the model's action normalisation (required with ``generator``).
        window_config: window options; default the training windows' for the model's
            sizes. Its ``dynamics`` (dt and bounds) must be the env's.
        threads: torch CPU threads while planning (restored after); None keeps torch's
            setting. One is the default: a cycle is hundreds of tiny ops, which extra
            threads only slow down (on CPU; irrelevant on a GPU).
    """

    phases = PHASES

    def __init__(
        self,
        k: int | str = 5,
        planning_interval: float = 0.5,
        target: str = "others",
        guidance_steps: int = 30,
        lambda_adv: float = 50.0,
        lambda_map: float = 1.0,
        guidance_horizon: int | None = None,
        step_size: float = GuidanceConfig.step_size,
        optimizer: str = GuidanceConfig.optimizer,
        rank_threshold: float = DEFAULT_THRESHOLD,
        seed: int = 0,
        device: torch.device | str = "cpu",
        generator: RiskFlowGenerator | None = None,
        normalizer: Normalizer | None = None,
        window_config: WindowConfig | None = None,
        threads: int | None = 1,
    ) -> None:
        self.check_options(k, planning_interval, threads)
        self.guidance = GuidanceConfig(
            steps=guidance_steps,
            step_size=step_size,
            lambda_adv=lambda_adv,
            lambda_map=lambda_map,
            horizon=guidance_horizon,
            target=target,
            optimizer=optimizer,
        )
        self.rank_threshold = float(rank_threshold)
        device = torch.device(device)
        if generator is None:
            if normalizer is not None:
                raise ValueError("normalizer given without its generator: pass both or neither")
            generator, normalizer = _load_shipped(device)
        elif normalizer is None:
            raise ValueError("a generator needs the normalizer it was trained with")
        self.model = generator.to(device).eval()
        self.normalizer = normalizer
        config = self.model.config
        window_config = window_config or WindowConfig(
            history_steps=config.history_steps,
            future_steps=config.future_steps,
            crop_size=config.map_size,
        )
        super().__init__(
            k, planning_interval, config.future_steps, window_config, seed, device, threads
        )

    def _plan_cycle(self, view: SceneView) -> None:
        """One cycle: window, encoder, one MeanFlow pass, ranking, guidance (module docstring)."""
        start = time.perf_counter()
        window = window_from_view(view, self.window_config)
        slots = window["agent_index"]
        batch = collate_windows([{key: window[key] for key in ENCODER_KEYS}])
        batch = {key: value.to(self.device) for key, value in batch.items()}
        clock = self._tick("window", start)
        with torch.no_grad():
            scene = self.model.encode(batch)
            clock = self._tick("encoder", clock)
            shape = (1, len(slots), self.model.config.future_steps, 2)
            eps = torch.randn(
                shape, generator=self._noise_source(), device=self.device, dtype=scene.context.dtype
            )
            self.noise = eps[0]
            u0 = base_velocity(self.model, eps, scene)[0]
            eps, state, agent_mask = eps[0], scene.state[0], scene.agent_mask[0]
            actions, trajectories = plans_from_velocity(
                eps, u0, state, agent_mask, self.normalizer, self.dynamics
            )
            done = torch.from_numpy(~view.active[slots]).to(self.device)
            hold_still(actions, trajectories, state, done)  # the env keeps them at speed 0
        clock = self._tick("generator", clock)
        self.ranking = rank_window(window, self.k, self.rank_threshold, view.active[slots])
        clock = self._tick("ranking", clock)
        ego = view.current[0]
        frame = np.array([ego[0], ego[1], ego[3]])
        guidance_scene = GuidanceScene(
            eps=eps,
            u0=u0,
            state=state,
            length=batch["length"][0],
            width=batch["width"][0],
            agent_mask=agent_mask,
            base_actions=actions,
            base_trajectories=trajectories,
            drivable_map=view.map,
            frame=torch.as_tensor(frame, dtype=state.dtype, device=self.device),
        )
        controllable = torch.from_numpy(self.ranking.controllable).to(self.device)
        result = guide(guidance_scene, controllable, self.normalizer, self.guidance, self.dynamics)
        self._tick("guidance", clock)
        self._store(view, slots, result.actions, result.trajectories, trajectories, frame)
        self.guidance_losses = result.losses.cpu().numpy()


def _load_shipped(device: torch.device) -> tuple[RiskFlowGenerator, Normalizer]:
    """The shipped generator and its normalizer (lazy import: training code is optional)."""
    try:
        from policies.riskflow.checkpoint import load_generator
    except ImportError as err:
        raise RuntimeError(
            "RiskFlowAdversary(generator=None) loads the shipped checkpoint through "
            f"policies.riskflow.checkpoint, which cannot be imported ({err}); pass "
            "generator= and normalizer= explicitly"
        ) from err
    model, normalizer, _ = load_generator(None, device=device)
    return model, normalizer


__all__ = ["BASE_COLOR", "GUIDED_COLOR", "PHASES", "RiskFlowAdversary"]
