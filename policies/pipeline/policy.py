"""``PipelinePolicy``: a receding-horizon scene policy that is a list of stages.

Every learned scene policy (RiskFlow, the unguided generator, STRIVE-style, the guided
diffusion baselines) drives every non-ego vehicle the same way, and differs only in the
stages of its planning cycle (:mod:`policies.pipeline.stages`):

* **schedule**: ``act`` re-plans every ``planning_interval`` (a multiple of ``dt``) and
  otherwise emits the next action of each plan (the plan buffer);
* **state**: what persists between cycles is one :class:`PlannerState` value per scene
  (``policy.state``), which a cycle takes and returns;
* **seeding**: the noise of cycle ``c`` of episode ``e`` (``reset`` count from 0) comes
  from a ``torch.Generator`` seeded with ``(seed, e, c)``, so the same seed gives the
  same closed-loop rollout, bit for bit, on one machine (same device and thread count);
* **many scenes**: :func:`~policies.pipeline.stages.plan_scenes` plans B scenes in one
  cycle, each scene a copy of the policy (:meth:`PipelinePolicy.spawn`: the model and
  options shared, the state its own); ``plan(view)`` is its case B = 1. Each scene's
  plans are those of planning it alone, to float rounding (padded batches run other kernels).
  :class:`~policies.pipeline.batched.BatchedAdversary` drives B scenes with it;
* **threads**: torch CPU threads while planning (restored after); timings per phase;
* **render overlays** of the plans (``draw``).

Vehicles that are live but got no window slot hold speed and heading (zero actions)
until a cycle gives them a plan; done vehicles stand still.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from policies.learned.adversary_config import AdversaryConfig
from policies.learned.encoder import SceneContext
from policies.learned.plan_stitching import resolve_stitch_steps
from policies.learned.window_types import WindowBatch
from policies.learned.windows import WindowConfig
from policies.pipeline import stages as stage_functions
from policies.pipeline.plan_set import PlanSet
from policies.pipeline.stages import plan_scenes
from policies.pipeline.state import PlannerState
from riskflow_env.agents.base import actions_dict, controlled_mask
from riskflow_env.config import is_integer
from riskflow_env.maps import MapStack
from riskflow_env.view import SceneView

BASE_COLOR = (70, 200, 235)  # overlay of the unguided plans
GUIDED_COLOR = (200, 80, 235)  # overlay of the guided (A_c) plans (purple: red marks collisions)

Stage = Callable[[Any, PlanSet], PlanSet]


class PipelinePolicy:
    """A scene policy whose planning cycle is ``stages`` (module docstring).

    Args:
        config: the shared options (K, planning interval, seed, device, threads, ...).
        horizon: plan length [steps].
        window_config: window options (its ``dynamics`` must be the env's).
        stages: the planning cycle, in order.
        encoder: the model's scene encoder, ``batch -> SceneContext``.
    """

    phases: tuple[str, ...] = ()
    overlay_prefix = "riskflow"

    def __init__(
        self,
        config: AdversaryConfig,
        horizon: int,
        window_config: WindowConfig,
        stages: Sequence[Stage],
        encoder: Callable[[WindowBatch], SceneContext],
        /,
    ) -> None:
        self.config = config
        self.k = config.k
        self.planning_interval = float(config.planning_interval)
        self.rank_threshold = float(config.rank_threshold)
        self.hold_distance = float(config.hold_distance)
        self.horizon = int(horizon)
        self.window_config = window_config
        self.dynamics = window_config.dynamics
        self.device = torch.device(config.device)
        self.threads = config.threads
        self.stages = tuple(stages)
        self.encoder = encoder
        blends_first = stage_functions.stitch in self.stages
        self.stitch_steps = resolve_stitch_steps(config.stitch_steps, blends_first)
        self.interval_steps = 0
        self.state = PlannerState(seed=config.seed)
        self._maps: dict[str, MapStack] = {}  # shared by spawned copies (the map stack)

    # --------------------------------------------------------- the state's fields
    seed = property(lambda self: self.state.seed, doc="noise seed of this scene")
    cycles = property(lambda self: self.state.cycles, doc="planning cycles this episode")
    plans = property(lambda self: self.state.plans, doc="(A, T, 4) world-frame plans")
    base_plans = property(lambda self: self.state.base_plans, doc="(A, T, 4) unguided plans")
    plan_actions = property(lambda self: self.state.plan_actions, doc="(A, T, 2) plan buffer")
    plan_mask = property(lambda self: self.state.plan_mask, doc="(A,) slots with a plan")
    controllable = property(lambda self: self.state.controllable, doc="(A,) A_c")
    ranking = property(lambda self: self.state.ranking, doc="how A_c was chosen")
    noise = property(lambda self: self.state.noise, doc="the cycle's noise")
    guidance_losses = property(lambda self: self.state.guidance_losses, doc="(N, 2) losses")
    timings = property(lambda self: self.state.timings, doc="[s] per phase and total")

    @property
    def controllable_names(self) -> tuple[str, ...]:
        """Names of the agents in ``A_c`` this cycle (set by the last ``act``)."""
        return tuple(self.state.names[i] for i in np.flatnonzero(self.state.controllable))

    # ----------------------------------------------------------- ScenePolicy
    def reseed(self, seed: int) -> None:
        """Restart the noise as a fresh policy built with ``seed`` (``EgoEnv.reset(seed=)``)."""
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be an int >= 0, got {seed!r}")
        self.state = self.state.restarted(seed=int(seed))

    def reset(self, view: SceneView) -> None:
        """New episode: drop the plans; the next ``act`` plans cycle 0."""
        interval = self.planning_interval / view.dt
        steps = round(interval)
        if not math.isclose(interval, steps, rel_tol=1e-6) or not 1 <= steps <= self.horizon:
            raise ValueError(
                f"planning_interval ({self.planning_interval} s) must be a multiple of dt "
                f"({view.dt} s) within [dt, {self.horizon} * dt]"
            )
        self.interval_steps = steps
        self.state = self.state.restarted().replace(episode=self.state.episode + 1)

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """The next action of each live non-ego vehicle's plan; re-plans on schedule."""
        if self.due(view):
            self.plan(view)
        return self.emit(view)

    def due(self, view: SceneView) -> bool:
        """Whether ``act(view)`` re-plans now: no plan yet, or ``planning_interval`` has
        passed since the last one (or the view is not a later step of it)."""
        if self.state.episode < 0:
            raise RuntimeError("call reset(view) before act(view)")
        step = self.state.plan_step
        return step is None or not 0 <= view.step - step < self.interval_steps

    def emit(self, view: SceneView) -> dict[str, np.ndarray]:
        """The actions of the stored plans at ``view.step`` (no re-planning)."""
        controlled = controlled_mask(view, "others")
        return actions_dict(view, controlled, self.emit_array(view, controlled))

    def emit_array(self, view: SceneView, controlled: np.ndarray | None = None) -> np.ndarray:
        """(A, 2) :meth:`emit` as one array per slot; zeros for the slots it does not drive
        (``controlled``: the view's non-ego live slots, ``controlled_mask(view, "others")``,
        computed when None)."""
        state = self.state
        if state.plan_step is None:
            raise RuntimeError("no plans yet: call act(view) (or plan(view)) first")
        elapsed = view.step - state.plan_step
        if not 0 <= elapsed < state.plan_actions.shape[1]:
            raise ValueError(
                f"view.step {view.step} is outside the stored plan (planned at step "
                f"{state.plan_step}, {state.plan_actions.shape[1]} steps)"
            )
        actions = np.zeros((view.num_agents, 2))
        if controlled is None:
            controlled = controlled_mask(view, "others")
        drive = state.plan_mask & controlled
        actions[drive] = state.plan_actions[drive, elapsed]
        return actions

    def spawn(self, seed: int | None = None) -> PipelinePolicy:
        """A copy for another scene: the same model and options (shared, not copied), its
        own state (``seed``; None: this policy's). Copies plan together in
        :func:`~policies.pipeline.stages.plan_scenes`; call ``reset`` on the copy first."""
        other = copy.copy(self)
        other.state = PlannerState(seed=self.state.seed)
        if seed is not None:
            other.reseed(seed)  # checks it
        return other

    def plan(self, view: SceneView) -> np.ndarray:
        """Run one planning cycle now (``act`` calls it on schedule); the plan buffer
        restarts at ``view.step``. The one-scene case of
        :func:`~policies.pipeline.stages.plan_scenes`.

        Returns:
            ``plans``: (A, T, 4) world-frame states (x, y [m], v [m/s], psi [rad]) after
            each plan step, per env slot; NaN rows for slots without a plan. The state
            also holds ``plan_actions`` (A, T, 2) (accel [m/s^2], yaw rate [rad/s]; zeros
            without a plan), ``base_plans`` (unguided), ``plan_mask`` (A,), ``controllable``
            (A,) (``A_c``), ``ranking``, ``noise``, ``guidance_losses`` ((N, 2): ``L_adv``,
            ``L_map`` per guidance step) and ``timings`` ([s] per phase, and ``"total"``).
        """
        plan_scenes([self], [view])
        return self.state.plans

    def predicted_states(self, view: SceneView, steps: int) -> np.ndarray:
        """What the current plans say each vehicle will do over the next ``steps`` steps:
        (A, steps, 4) world-frame states; past the end of a plan its last state holds; NaN
        rows for slots without a plan."""
        state = self.state
        if state.plans is None or state.plan_step is None:
            raise RuntimeError("no plans yet: call act(view) before predicted_states(view)")
        if not (is_integer(steps) and steps >= 1):
            raise ValueError(f"steps must be an int >= 1, got {steps!r}")
        elapsed = view.step - state.plan_step
        index = np.minimum(np.arange(elapsed, elapsed + steps), state.plans.shape[1] - 1)
        return state.plans[:, index]

    def draw(self, renderer) -> None:
        """Push this cycle's plans to a renderer (``SceneRenderer.set_overlay``): the plans
        of the unguided vehicles, and the guided plans of ``A_c``, haloed."""
        state = self.state
        if state.plans is None:
            return
        others = state.plan_mask & ~state.controllable
        prefix = self.overlay_prefix
        xy = state.plans[..., :2]
        renderer.set_overlay(f"{prefix}_base", xy, others, BASE_COLOR, label="base plans")
        renderer.set_overlay(
            f"{prefix}_guided", xy, state.controllable, GUIDED_COLOR,
            highlight=tuple(int(i) for i in np.flatnonzero(state.controllable)),
            label="guided plans (A_c, haloed)",
        )  # fmt: skip


__all__ = ["BASE_COLOR", "GUIDED_COLOR", "PipelinePolicy", "Stage", "plan_scenes"]
