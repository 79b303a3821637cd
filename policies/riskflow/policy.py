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
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from policies.base import actions_dict, controlled_mask
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
from policies.riskflow.ranking import DEFAULT_THRESHOLD, Ranking, check_k, rank_window
from policies.riskflow.sampler import base_velocity
from riskflow_env.scenarios.windows import WindowConfig, window_from_view
from riskflow_env.view import SceneView

BASE_COLOR = (70, 200, 235)  # overlay of the unguided plans
GUIDED_COLOR = (235, 35, 35)  # overlay of the guided (A_c) plans
PHASES = ("window", "encoder", "generator", "ranking", "guidance")


class RiskFlowAdversary:
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
        self.k = check_k(k)
        if not (isinstance(planning_interval, (int, float)) and planning_interval > 0):
            raise ValueError(f"planning_interval must be > 0 [s], got {planning_interval!r}")
        if threads is not None and (not isinstance(threads, int) or threads < 1):
            raise ValueError(f"threads must be None or an int >= 1, got {threads!r}")
        self.planning_interval = float(planning_interval)
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
        self.seed = int(seed)
        self.device = torch.device(device)
        self.threads = threads
        if generator is None:
            if normalizer is not None:
                raise ValueError("normalizer given without its generator: pass both or neither")
            generator, normalizer = _load_shipped(self.device)
        elif normalizer is None:
            raise ValueError("a generator needs the normalizer it was trained with")
        self.model = generator.to(self.device).eval()
        self.normalizer = normalizer
        config = self.model.config
        self.window_config = window_config or WindowConfig(
            history_steps=config.history_steps,
            future_steps=config.future_steps,
            crop_size=config.map_size,
        )
        self.dynamics = self.window_config.dynamics
        self._episode = -1
        self._clear()

    # ----------------------------------------------------------- ScenePolicy
    def reset(self, view: SceneView) -> None:
        """New episode: drop the plans; the next ``act`` plans cycle 0."""
        interval = self.planning_interval / view.dt
        steps = round(interval)
        if not math.isclose(interval, steps, rel_tol=1e-6) or not (
            1 <= steps <= self.model.config.future_steps
        ):
            raise ValueError(
                f"planning_interval ({self.planning_interval} s) must be a multiple of dt "
                f"({view.dt} s) within [dt, {self.model.config.future_steps} * dt]"
            )
        self.interval_steps = steps
        self._episode += 1
        self._clear()

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """The next action of each live non-ego vehicle's plan; re-plans on schedule."""
        if self._episode < 0:
            raise RuntimeError("call reset(view) before act(view)")
        elapsed = None if self._plan_step is None else view.step - self._plan_step
        if elapsed is None or not 0 <= elapsed < self.interval_steps:
            self.plan(view)
            elapsed = 0
        actions = np.zeros((view.num_agents, 2))
        actions[self.plan_mask] = self.plan_actions[self.plan_mask, elapsed]
        return actions_dict(view, controlled_mask(view, "others"), actions)

    # -------------------------------------------------------------- planning
    def _clear(self) -> None:
        self._plan_step: int | None = None
        self.cycles = 0
        self.plans: np.ndarray | None = None
        self.plan_actions = np.zeros((0, 0, 2))
        self.noise: torch.Tensor | None = None
        self.base_plans: np.ndarray | None = None
        self.plan_mask = np.zeros(0, dtype=bool)
        self.controllable = np.zeros(0, dtype=bool)
        self.ranking: Ranking | None = None
        self.guidance_losses: np.ndarray | None = None
        self.timings: dict[str, float] = {}
        self._names: tuple[str, ...] = ()

    def _noise_source(self) -> torch.Generator:
        seed = int(
            np.random.SeedSequence([self.seed, self._episode, self.cycles]).generate_state(1)[0]
        )
        return torch.Generator(device=self.device).manual_seed(seed)

    def _tick(self, phase: str, start: float) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        now = time.perf_counter()
        self.timings[phase] = now - start
        return now

    def plan(self, view: SceneView) -> np.ndarray:
        """Run one planning cycle now (``act`` calls it on schedule); the plan buffer
        restarts at ``view.step``.

        Returns:
            ``plans``: (A, T, 4) world-frame states (x, y [m], v [m/s], psi [rad]) after
            each plan step, per env slot; NaN rows for slots without a plan. Also sets
            ``plan_actions`` (A, T, 2) (accel [m/s^2], yaw rate [rad/s]; zeros without a
            plan), ``base_plans`` (unguided), ``plan_mask`` (A,) (slots with a plan),
            ``controllable`` (A,) (``A_c``), ``ranking`` (window slots), ``noise`` (the
            cycle's ``eps``, (A_window, T, 2), window slot order), ``guidance_losses``
            (K_g + 1, 2) and ``timings`` ([s] per phase of :data:`PHASES`, and ``"total"``).
        """
        if self._episode < 0:
            raise RuntimeError("call reset(view) before plan(view)")
        previous_threads = torch.get_num_threads()
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        try:
            self._plan_cycle(view)
        finally:
            if self.threads is not None:
                torch.set_num_threads(previous_threads)
        return self.plans

    def _plan_cycle(self, view: SceneView) -> None:
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
            actions[done] = 0.0  # done vehicles stand still (the env keeps them at speed 0)
            standing = state.clone()
            standing[:, 2] = 0.0
            trajectories[done] = standing[done, None].expand_as(trajectories[done])
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
        self.timings["total"] = time.perf_counter() - start
        self._store(view, slots, result.actions, result.trajectories, trajectories, frame)
        self.guidance_losses = result.losses.cpu().numpy()
        self._plan_step = view.step
        self.cycles += 1

    def _store(
        self,
        view: SceneView,
        slots: np.ndarray,
        actions: torch.Tensor,
        guided: torch.Tensor,
        base: torch.Tensor,
        frame: np.ndarray,
    ) -> None:
        """Plans in env slot order, world frame; NaN rows for slots without a plan."""
        num, steps = view.num_agents, actions.shape[1]
        self.plan_actions = np.zeros((num, steps, 2))
        self.plan_actions[slots] = actions.cpu().numpy()
        self._names = view.agent_names
        self.plan_mask = np.zeros(num, dtype=bool)
        self.plan_mask[slots] = True
        self.controllable = np.zeros(num, dtype=bool)
        self.controllable[slots] = self.ranking.controllable
        self.plans, self.base_plans = (
            _to_world(t.cpu().numpy(), slots, num, frame) for t in (guided, base)
        )

    # ------------------------------------------------------------ rendering
    @property
    def controllable_names(self) -> tuple[str, ...]:
        """Names of the agents in ``A_c`` this cycle (set by the last ``act``)."""
        return tuple(self._names[i] for i in np.flatnonzero(self.controllable))

    def draw(self, renderer) -> None:
        """Push this cycle's plans to a renderer (``SceneRenderer.set_overlay``): base plans
        of the unguided vehicles, guided plans of ``A_c`` (highlighted)."""
        if self.plans is None:
            return
        others = self.plan_mask & ~self.controllable
        renderer.set_overlay("riskflow_base", self.plans[..., :2], others, BASE_COLOR)
        renderer.set_overlay(
            "riskflow_guided",
            self.plans[..., :2],
            self.controllable,
            GUIDED_COLOR,
            highlight=tuple(int(i) for i in np.flatnonzero(self.controllable)),
        )


def _to_world(plans: np.ndarray, slots: np.ndarray, num: int, frame: np.ndarray) -> np.ndarray:
    """(num, T, 4) world-frame states from scene-frame ``plans`` (A, T, 4) of ``slots``."""
    cos, sin = math.cos(frame[2]), math.sin(frame[2])
    out = np.full((num, plans.shape[1], 4), np.nan)
    x, y = plans[..., 0].astype(np.float64), plans[..., 1].astype(np.float64)
    out[slots, :, 0] = frame[0] + cos * x - sin * y
    out[slots, :, 1] = frame[1] + sin * x + cos * y
    out[slots, :, 2] = plans[..., 2]
    out[slots, :, 3] = plans[..., 3] + frame[2]
    return out


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


__all__ = ["PHASES", "RiskFlowAdversary"]
