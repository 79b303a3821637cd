"""``PlanBufferPolicy``: the receding-horizon machinery shared by the learned adversaries.

A subclass implements :meth:`PlanBufferPolicy._plan_cycles` (``RiskFlowAdversary``: B
scenes in one encoder pass, one generator pass and one guidance loop) or
:meth:`PlanBufferPolicy._plan_cycle` (one scene; the diffusion baselines'
``DiffusionAdversary``): from the views, plan every window slot and call
:meth:`PlanBufferPolicy._store` on each scene's policy copy. This base does the rest:

* **many scenes**: :func:`plan_scenes` plans B scenes in one call, each scene a copy of
  the policy (:meth:`PlanBufferPolicy.spawn`: the model and options shared; plan buffer,
  schedule, episode count and noise stream its own); ``plan(view)`` is its case B = 1
  and ``act`` re-plans through it (``due``, then ``emit``).
  :class:`~policies.learned.batched_adversary.BatchedAdversary` drives B scenes with it;
* **schedule**: ``act`` re-plans every ``planning_interval`` (a multiple of ``dt``) and
  otherwise emits the next action of each plan (the plan buffer);
* **seeding**: the noise of cycle ``c`` of episode ``e`` (``reset`` count from 0) comes
  from a ``torch.Generator`` seeded with ``(seed, e, c)`` (:meth:`_noise_source`), so
  the same seed gives the same closed-loop rollout, bit for bit, on one machine;
* **observation**: :meth:`PlanBufferPolicy._encode_views` cuts each scene's window from
  its view, collates them and runs the model's scene encoder once (the ``"window"`` and
  ``"encoder"`` phases of every subclass; :mod:`policies.learned.encoded_views`);
* **threads**: torch CPU threads while planning (restored after);
* **timings** per phase, world-frame plans and the controllable set;
* **stitching** (:mod:`policies.learned.plan_stitching`): a new plan's first
  ``stitch_steps`` actions are blended with the plan being executed, so the actions stay
  continuous across a re-plan (``stitch_steps=0`` switches at once); before
  that, with ``hold_distance`` > 0, vehicles at rest whose plan hardly moves them keep their brake
  on (same module);
* **render overlays** of the plans (:mod:`policies.learned.plan_overlay`).

The constructors' shared checks (:func:`~policies.learned.adversary_config.check_model_pair`,
:func:`~policies.learned.adversary_config.default_window_config`) live with
:class:`~policies.learned.adversary_config.AdversaryConfig`; this module re-exports them.

Vehicles that are live but got no window slot hold speed and heading (zero actions)
until a cycle gives them a plan; done vehicles stand still (:func:`hold_still`).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch

from policies.learned.adversary_config import (
    AdversaryConfig,
    check_model_pair,
    default_window_config,
)
from policies.learned.encoded_views import EncodedView, EncodedViews, encode_views
from policies.learned.encoder import SceneContext
from policies.learned.plan_overlay import BASE_COLOR, GUIDED_COLOR, PlanOverlay
from policies.learned.plan_stitching import PlanStitching, resolve_stitch_steps
from policies.learned.ranking import Ranking
from policies.learned.window_types import WindowBatch
from policies.learned.windows import WindowConfig, scene_to_world
from riskflow_env.agents.base import actions_dict, controlled_mask
from riskflow_env.maps import DrivableMap, MapStack
from riskflow_env.view import SceneView


def hold_still(
    actions: torch.Tensor, trajectories: torch.Tensor, state: torch.Tensor, done: torch.Tensor
) -> None:
    """In place: ``done`` rows get zero actions and stand at their current pose, speed 0
    (the env keeps done vehicles as obstacles). Shapes (A, T, 2), (A, T, 4), (A, 4), (A,),
    or with a leading scene axis B on each."""
    actions[done] = 0.0
    standing = state.clone()
    standing[..., 2] = 0.0
    trajectories[done] = standing[done, None].expand_as(trajectories[done])


class PlanBufferPolicy(PlanStitching, PlanOverlay):
    """Base of the plan-buffer scene policies (module docstring); drives every non-ego vehicle.

    Args:
        config: the shared options (K, planning interval, seed, device, threads, ...).
        horizon: plan length [steps].
        window_config: window options (its ``dynamics`` must be the env's).
    """

    phases: tuple[str, ...] = ()

    def __init__(
        self, config: AdversaryConfig, horizon: int, window_config: WindowConfig, /
    ) -> None:
        self.config = config
        self.k = config.k
        self.planning_interval = float(config.planning_interval)
        self.rank_threshold = float(config.rank_threshold)
        self.horizon = int(horizon)
        self.window_config = window_config
        self.dynamics = window_config.dynamics
        self.seed = config.seed
        self.hold_distance = float(config.hold_distance)
        self.stitch_steps = resolve_stitch_steps(config.stitch_steps, self.stitch_first)
        self.device = torch.device(config.device)
        self.threads = config.threads
        self._episode = -1
        self._shared: dict[str, object] = {}  # shared by spawned copies (the map stack)
        self._clear()

    # ----------------------------------------------------------- ScenePolicy
    def reseed(self, seed: int) -> None:
        """Restart the noise as a fresh policy built with ``seed`` (``EgoEnv.reset(seed=)``)."""
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be an int >= 0, got {seed!r}")
        self.seed = int(seed)
        self._episode = -1

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
        self._episode += 1
        self._clear()

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """The next action of each live non-ego vehicle's plan; re-plans on schedule."""
        if self.due(view):
            self.plan(view)
        return self.emit(view)

    def due(self, view: SceneView) -> bool:
        """Whether ``act(view)`` re-plans now: no plan yet, or ``planning_interval`` has
        passed since the last one (or the view is not a later step of it)."""
        if self._episode < 0:
            raise RuntimeError("call reset(view) before act(view)")
        elapsed = None if self._plan_step is None else view.step - self._plan_step
        return elapsed is None or not 0 <= elapsed < self.interval_steps

    def emit(self, view: SceneView) -> dict[str, np.ndarray]:
        """The actions of the stored plans at ``view.step`` (no re-planning)."""
        return actions_dict(view, controlled_mask(view, "others"), self.emit_array(view))

    def emit_array(self, view: SceneView) -> np.ndarray:
        """(A, 2) :meth:`emit` as one array per slot; zeros for the slots it does not drive."""
        if self._plan_step is None:
            raise RuntimeError("no plans yet: call act(view) (or plan(view)) first")
        elapsed = view.step - self._plan_step
        if not 0 <= elapsed < self.plan_actions.shape[1]:
            raise ValueError(
                f"view.step {view.step} is outside the stored plan (planned at step "
                f"{self._plan_step}, {self.plan_actions.shape[1]} steps)"
            )
        actions = np.zeros((view.num_agents, 2))
        drive = self.plan_mask & controlled_mask(view, "others")
        actions[drive] = self.plan_actions[drive, elapsed]
        return actions

    def spawn(self, seed: int | None = None) -> PlanBufferPolicy:
        """A copy for another scene: the same model and options (shared, not copied), its
        own plan buffer, episode count and noise stream (``seed``; None: this policy's).
        Copies plan together in :func:`plan_scenes`; call ``reset`` on the copy first."""
        other = copy.copy(self)
        other._episode = -1
        other._clear()
        if seed is not None:
            other.reseed(seed)
        return other

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
        restarts at ``view.step``. The one-scene case of :func:`plan_scenes`.

        Returns:
            ``plans``: (A, T, 4) world-frame states (x, y [m], v [m/s], psi [rad]) after
            each plan step, per env slot; NaN rows for slots without a plan. Also sets
            ``plan_actions`` (A, T, 2) (accel [m/s^2], yaw rate [rad/s]; zeros without a
            plan), ``base_plans`` (unguided), ``plan_mask`` (A,) (slots with a plan),
            ``controllable`` (A,) (``A_c``), ``ranking`` (window slots), ``noise`` (the
            cycle's noise, window slot order), ``guidance_losses`` ((N, 2): ``L_adv``,
            ``L_map`` per guidance step) and ``timings`` ([s] per phase of ``phases``,
            and ``"total"``).
        """
        plan_scenes([self], [view])
        return self.plans

    def predicted_states(self, view: SceneView, steps: int) -> np.ndarray:
        """What the current plans say each vehicle will do over the next ``steps`` steps.

        Args:
            view: the current scene (``act(view)`` has run for it, so the plans are live).
            steps: how far ahead [env steps]; past the end of a plan its last state holds.

        Returns:
            (A, steps, 4) world-frame states (x, y [m], v [m/s], psi [rad]) after each of
            the next ``steps`` steps; NaN rows for slots without a plan.
        """
        if self.plans is None or self._plan_step is None:
            raise RuntimeError("no plans yet: call act(view) before predicted_states(view)")
        if not (isinstance(steps, int) and steps >= 1):
            raise ValueError(f"steps must be an int >= 1, got {steps!r}")
        elapsed = view.step - self._plan_step
        index = np.minimum(np.arange(elapsed, elapsed + steps), self.plans.shape[1] - 1)
        return self.plans[:, index]

    def _encode_views(
        self,
        views: Sequence[SceneView],
        encode: Callable[[WindowBatch], SceneContext],
    ) -> EncodedViews:
        """:func:`~policies.learned.encoded_views.encode_views` with this policy's window
        options, device and phase clock (phases ``"window"`` and ``"encoder"``)."""
        return encode_views(views, self.window_config, self.device, encode, self._tick)

    def _encode_view(
        self, view: SceneView, encode: Callable[[WindowBatch], SceneContext]
    ) -> EncodedView:
        """:meth:`_encode_views` of one scene."""
        return self._encode_views([view], encode).view(0)

    def _map_of(self, views: Sequence[SceneView]) -> DrivableMap | MapStack:
        """The scenes' maps for one lookup: their shared map, or a :class:`MapStack` in
        scene order. The stack is kept (shared with spawned copies) and reused while it
        holds every map asked for; :meth:`prepare_maps` fills it for a whole batch."""
        maps = [view.map for view in views]
        if all(m is maps[0] for m in maps):
            return maps[0]
        stack = self._shared.get("maps")
        if stack is None or not all(id(m) in stack.positions for m in maps):
            stack = self.prepare_maps(maps)
        return stack.view([stack.positions[id(m)] for m in maps])

    def prepare_maps(self, maps: Sequence[DrivableMap]) -> MapStack:
        """Stack ``maps`` (distinct ones, in order) for :meth:`_map_of` (kept until a map
        outside them is asked for)."""
        unique = list({id(m): m for m in maps}.values())
        stack = self._shared.get("maps")
        if stack is None or [id(m) for m in stack.maps] != [id(m) for m in unique]:
            stack = MapStack(unique)
            self._shared["maps"] = stack
        return stack

    def _plan_cycles(self, scenes: Sequence[PlanBufferPolicy], views: Sequence[SceneView]) -> None:
        """Plan every window slot of each scene and :meth:`_store` the plans on each
        ``scenes[b]`` (``self`` is ``scenes[0]``, the planner). Subclasses that plan B
        scenes in one pass override this; the default plans them one by one with
        :meth:`_plan_cycle`."""
        for scene, view in zip(scenes, views, strict=True):
            scene._plan_cycle(view)

    def _plan_cycle(self, view: SceneView) -> None:
        """Plan every window slot of one scene and :meth:`_store` the plans (subclasses
        implement this or :meth:`_plan_cycles`)."""
        raise NotImplementedError(f"{type(self).__name__} implements no planning cycle")

    def _store(
        self,
        view: SceneView,
        slots: np.ndarray,
        actions: torch.Tensor,
        guided: torch.Tensor,
        base: torch.Tensor,
        frame: np.ndarray,
    ) -> None:
        """Plans in env slot order, world frame; NaN rows for slots without a plan.

        Args: window ``slots`` (A_w,); ``actions`` (A_w, T, 2); ``guided`` and ``base``
        (A_w, T, 4) scene-frame states; ``frame`` (3,) world pose of the scene frame.
        """
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


def plan_scenes(scenes: Sequence[PlanBufferPolicy], views: Sequence[SceneView]) -> None:
    """One planning call for B scenes: ``scenes[b]`` plans ``views[b]`` now.

    ``scenes`` are copies of one policy (:meth:`PlanBufferPolicy.spawn`, or the policy
    itself): the same model and options, each with its own plan buffer, episode and noise
    stream, so each scene's noise and plans are those of planning it alone (to float
    rounding: padded batches run other kernels). A subclass with a batched
    :meth:`~PlanBufferPolicy._plan_cycles` runs one encoder pass for all of them and
    then its own batched cycle (``RiskFlowAdversary``: one generator pass and one
    guidance loop; ``StriveAdversary``: one latent optimisation; ``DiffusionAdversary``:
    one base chain and one guided chain); a subclass that implements only
    :meth:`~PlanBufferPolicy._plan_cycle` plans them scene by scene. Then each scene's
    new plans are stitched onto its executed ones and its buffer restarts at its
    ``view.step`` (vehicles at rest held first, with ``hold_distance`` > 0).
    ``PlanBufferPolicy.plan`` is the case B = 1.

    Every scene's ``timings`` are the call's: its phases (they ran once for all scenes;
    for a subclass that plans scene by scene, those of ``scenes[0]``) and its ``"total"``.

    Raises:
        ValueError: ``scenes`` and ``views`` differ in length or are empty, or the scenes
            are not copies of one policy.
        RuntimeError: a scene was not ``reset``.
    """
    scenes, views = list(scenes), list(views)
    if not scenes or len(scenes) != len(views):
        raise ValueError(
            f"scenes and views must be non-empty and of equal length, got {len(scenes)} "
            f"scenes and {len(views)} views"
        )
    planner = scenes[0]
    for scene in scenes:
        if type(scene) is not type(planner) or scene._shared is not planner._shared:
            raise ValueError("scenes must be copies of one policy (PlanBufferPolicy.spawn)")
        if scene._episode < 0:
            raise RuntimeError("call reset(view) before plan(view)")
    if len({id(scene) for scene in scenes}) != len(scenes):
        raise ValueError("scenes must be distinct policy copies (one per scene)")
    previous_threads = torch.get_num_threads()
    if planner.threads is not None:
        torch.set_num_threads(planner.threads)
    try:
        start = time.perf_counter()
        before = [
            None
            if scene._plan_step is None
            else (scene.plan_actions, scene.plan_mask, view.step - scene._plan_step)
            for scene, view in zip(scenes, views, strict=True)
        ]
        planner._plan_cycles(scenes, views)
        for scene, view, previous in zip(scenes, views, before, strict=True):
            scene._shape(view)
            if previous is not None and scene.stitch_steps > 0:
                scene._stitch(view, *previous, guided_only=scene.stitch_first)
        total = time.perf_counter() - start
    finally:
        if planner.threads is not None:
            torch.set_num_threads(previous_threads)
    timings = dict(planner.timings, total=total)
    for scene, view in zip(scenes, views, strict=True):
        scene.timings = dict(timings)
        scene._plan_step = view.step
        scene.cycles += 1


def _to_world(plans: np.ndarray, slots: np.ndarray, num: int, frame: np.ndarray) -> np.ndarray:
    """(num, T, 4) world-frame states from scene-frame ``plans`` (A, T, 4) of ``slots``."""
    out = np.full((num, plans.shape[1], 4), np.nan)
    out[slots] = scene_to_world(plans, frame)
    return out


__all__ = [
    "BASE_COLOR",
    "GUIDED_COLOR",
    "EncodedView",
    "EncodedViews",
    "PlanBufferPolicy",
    "check_model_pair",
    "default_window_config",
    "hold_still",
    "plan_scenes",
]
