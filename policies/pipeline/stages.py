"""The stages of a planning cycle, shared by every learned scene policy.

A stage is a function ``stage(policy, plans) -> plans`` over one :class:`PlanSet` of B
scenes; ``policy`` supplies the model and the options. A method is its list of stages
(:func:`plan_scenes`, below, runs them in order for B scenes)::

    RiskFlow       encode rank generate stitch avoid stand guide emit hold restitch
    unguided       encode      generate stitch avoid stand       emit hold restitch
    STRIVE-style   as RiskFlow, with the latent optimisation as ``guide``
    raw variants   ``decode`` in place of ``avoid``; no ``hold``
    diffusion      encode select chain                           emit hold restitch

* ``encode``: windows (ego frame) of every scene, collated, one encoder pass;
* ``rank``: the TTC causal ranking, ``A_c`` (:mod:`policies.learned.ranking`);
* ``generate``: each scene's noise from its own stream, one generator pass, ``u0``;
* ``stitch``: each new base plan blended into the executed one (blending first);
* ``decode``: actions and their rollout from ``eps + u`` (``avoid`` decodes its own);
* ``avoid``: the avoidance steps (:mod:`policies.learned.plan_avoidance`);
* ``stand``: done vehicles stand still (the env keeps them at speed 0);
* ``guide``: the method's own (RiskFlow: output-space guidance of the ``A_c`` rows,
  :func:`policies.riskflow.guidance.guide_outputs`);
* ``emit``: the plans into each scene's new planner state, world frame, numpy;
* ``hold``: vehicles at rest keep their brake on; ``restitch``: the rows not blended first
  (the guided ones, or all of them) blended into the executed plans
  (:mod:`policies.learned.plan_stitching`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from policies.learned.guidance_losses import Target, map_term, target_rows
from policies.learned.packing import exact_scene_widths
from policies.learned.plan_avoidance import avoid_overlaps, guided_pairs
from policies.learned.plan_overlap import OVERLAP_HORIZON
from policies.learned.plan_stitching import blend_first, hold_at_rest, stitch_after
from policies.learned.ranking import rank_window
from policies.learned.sampler import base_velocity, decode_plans
from policies.learned.windows import cut_windows, scene_to_world
from policies.pipeline.plan_set import EncodedViews, PlanSet
from policies.pipeline.state import PlannerState
from riskflow_env.maps import DrivableMap, MapStack
from riskflow_env.view import SceneView

PipelinePolicy = Any  # policies.pipeline.policy.PipelinePolicy, which runs the stages


def encode(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """Windows of every scene (numpy, scene by scene), collated (agents padded), one
    encoder pass; phases ``"window"`` and ``"encoder"``."""
    start = time.perf_counter()
    views = plans.views
    windows, batch = cut_windows(views, policy.window_config, policy.device)
    clock = policy.clock.tick("window", start)
    with torch.no_grad():
        scene = policy.encoder(batch)
    clock = policy.clock.tick("encoder", clock)
    frames = np.array([[v.current[0, 0], v.current[0, 1], v.current[0, 3]] for v in views])
    slots = [window.agent_index for window in windows]
    observed = EncodedViews(windows, slots, batch, scene, frames, clock)
    return plans.replace(observed=observed)


def rank(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """``A_c`` of each scene by the TTC causal ranking of its window (numpy, scene by
    scene); done vehicles are never in it. With target ``"ego"``, one attacker at most,
    kept from the last cycle while it is eligible (:func:`~policies.learned.ranking.
    ego_attacker`)."""
    observed = plans.observed
    controllable = np.zeros(observed.scene.agent_mask.shape, dtype=bool)
    rankings = []
    attack_ego = policy.guidance.target == Target.EGO
    for index, (view, state) in enumerate(zip(plans.views, plans.states, strict=True)):
        window, slots = observed.windows[index], observed.slots[index]
        ranking = rank_window(
            window, policy.k, policy.rank_threshold, view.active[slots],
            attack_ego=attack_ego, attacker=attacker_row(state, slots) if attack_ego else None,
        )  # fmt: skip
        controllable[index, : len(slots)] = ranking.controllable
        rankings.append(ranking)
    controllable = torch.from_numpy(controllable).to(policy.device)
    return plans.replace(controllable=controllable, rankings=rankings)


def attacker_row(state: PlannerState, slots: np.ndarray) -> int | None:
    """The window row of the last cycle's attacker (``state.controllable``, env slots),
    or None (no attacker, or it has no row now)."""
    chosen = np.flatnonzero(state.controllable)
    rows = np.flatnonzero(np.isin(slots, chosen))
    return int(rows[0]) if rows.size else None


def generate(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """Each scene's noise from its own stream, with the shape it has alone, and one
    generator pass for all: ``u0 = u_theta(eps, 0, 1; C)``."""
    scene = plans.observed.scene
    num_scenes, num_agents = scene.agent_mask.shape
    steps = policy.horizon
    with torch.no_grad():
        eps = scene.context.new_zeros(num_scenes, num_agents, steps, 2)
        for index, (state, count) in enumerate(
            zip(plans.states, plans.observed.counts, strict=True)
        ):
            eps[index, :count] = torch.randn(
                (count, steps, 2),
                generator=state.noise_source(policy.device),
                device=policy.device,
                dtype=scene.context.dtype,
            )
        u0 = base_velocity(policy.model, eps, scene)
    return plans.replace(eps=eps, u=u0)


def stitch(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """Blend each new base plan into the plan being executed (blending first,
    :func:`~policies.learned.plan_stitching.blend_first`): ``u`` of plans whose first
    actions are the blend, and the gain of the avoidance steps' corrections."""
    u, gain = blend_first(
        plans.states, plans.views, plans.observed.slots, plans.eps, plans.u,
        policy.normalizer, policy.stitch_steps,
    )  # fmt: skip
    return plans.replace(u=u, gain=gain)


def decode(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """The base plans: actions ``clip(denorm(eps + u))`` and their rollout."""
    scene = plans.observed.scene
    with torch.no_grad():
        actions, trajectories = decode_plans(
            plans.eps + plans.u, scene.state, scene.agent_mask, policy.normalizer,
            policy.dynamics,
        )  # fmt: skip
    return plans.replace(base_actions=actions, base_trajectories=trajectories)


def avoid(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """The avoidance steps on every scene's base plans
    (:func:`~policies.learned.plan_avoidance.avoid_overlaps`). The pairs of a vehicle of
    ``A_c`` and one of its targets are left to guidance, when it pulls them together."""
    observed, controllable = plans.observed, plans.controllable
    scene, batch = observed.scene, observed.batch
    exempt = None
    if controllable is not None and policy.guidance.lambda_adv > 0 and bool(controllable.any()):
        targets = target_rows(scene.agent_mask, controllable, 0, policy.guidance.target)
        exempt = guided_pairs(controllable, targets)
    num_agents = scene.agent_mask.shape[1]
    flat = SimpleNamespace(
        length=batch.length.flatten(), width=batch.width.flatten(),
        drivable_map=plans.drivable_map, frame=observed.frame_tensor(),
    )  # fmt: skip

    def map_term_of(rows: torch.Tensor):  # every step of its own horizon, not T_g's
        return map_term(
            flat, rows, OVERLAP_HORIZON, policy.guidance, rows // num_agents, OVERLAP_HORIZON
        )

    with torch.no_grad():
        u0, actions, trajectories = avoid_overlaps(
            plans.eps, plans.u, scene.state, batch.length, batch.width, scene.agent_mask,
            map_term_of, policy.normalizer, policy.dynamics, steps=policy.avoid_steps,
            step_size=policy.avoid_step_size, gain=plans.gain, exempt=exempt,
            guided=controllable,
        )  # fmt: skip
    return plans.replace(u=u0, base_actions=actions, base_trajectories=trajectories)


def stand(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """Done vehicles stand still in the base plans: zero actions, their current pose at
    speed 0 (the env keeps them as obstacles)."""
    scene = plans.observed.scene
    done = np.zeros(scene.agent_mask.shape, dtype=bool)
    for index, (view, slots) in enumerate(zip(plans.views, plans.observed.slots, strict=True)):
        done[index, : len(slots)] = ~view.active[slots]
    done = torch.from_numpy(done).to(policy.device)
    stand_still(plans.base_actions, plans.base_trajectories, scene.state, done)
    return plans


def stand_still(
    actions: torch.Tensor, trajectories: torch.Tensor, state: torch.Tensor, done: torch.Tensor
) -> None:
    """In place: ``done`` rows get zero actions and stand at their current pose, speed 0.
    Shapes (..., A, T, 2), (..., A, T, 4), (..., A, 4), (..., A)."""
    actions[done] = 0.0
    standing = state.clone()
    standing[..., 2] = 0.0
    trajectories[done] = standing[done, None].expand_as(trajectories[done])


def emit(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """Each scene's new planner state: its plans in env slot order, world frame, numpy
    (NaN rows for slots without a plan); the cycle's noise, ranking and losses."""
    observed = plans.observed
    num_scenes = len(plans.views)
    actions = plans.base_actions if plans.actions is None else plans.actions
    trajectories = plans.base_trajectories if plans.trajectories is None else plans.trajectories
    losses = plans.losses
    if losses is None:  # nothing guided: zero losses before the (absent) first step
        losses = torch.zeros(1, num_scenes, 2, dtype=plans.base_actions.dtype)
    losses = losses.cpu().numpy()
    controllable = plans.controllable
    new_states = []
    for index, (state, view) in enumerate(zip(plans.states, plans.views, strict=True)):
        slots, num = observed.slots[index], view.num_agents
        rows = slice(0, len(slots))
        plan_actions = np.zeros((num, policy.horizon, 2))
        plan_actions[slots] = actions[index, rows].cpu().numpy()
        base_actions = np.zeros((num, policy.horizon, 2))
        base_actions[slots] = plans.base_actions[index, rows].cpu().numpy()
        plan_mask = np.zeros(num, dtype=bool)
        plan_mask[slots] = True
        chosen = np.zeros(num, dtype=bool)
        if controllable is not None:
            chosen[slots] = controllable[index, rows].cpu().numpy()
        frame = observed.frames[index]
        new_states.append(
            state.replace(
                plan_actions=plan_actions,
                plans=world_plans(trajectories[index, rows].cpu().numpy(), slots, num, frame),
                base_plans=world_plans(
                    plans.base_trajectories[index, rows].cpu().numpy(), slots, num, frame
                ),
                base_actions=base_actions,
                plan_mask=plan_mask,
                controllable=chosen,
                names=view.agent_names,
                ranking=plans.rankings[index] if plans.rankings else None,
                noise=plans.eps[index, rows] if plans.noise is None else plans.noise[index],
                guidance_losses=losses[:, index],
                extras=dict(plans.extras[index]) if plans.extras else {},
            )
        )
    return plans.replace(new_states=new_states)


def world_plans(plans: np.ndarray, slots: np.ndarray, num: int, frame: np.ndarray) -> np.ndarray:
    """(num, T, 4) world-frame states from scene-frame ``plans`` (A_w, T, 4) of the env
    ``slots``; NaN rows for the other slots."""
    out = np.full((num, plans.shape[1], 4), np.nan)
    out[slots] = scene_to_world(plans, frame)
    return out


def hold(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """Vehicles at rest whose new plan hardly moves them keep their brake on."""
    for state, view in zip(plans.new_states, plans.views, strict=True):
        hold_at_rest(state, view, policy.hold_distance, policy.dynamics)
    return plans


def restitch(policy: PipelinePolicy, plans: PlanSet) -> PlanSet:
    """The new plans not blended before planning (the guided rows of a method that blends
    first, every row of one that does not) blended into the executed plans."""
    guided_only = stitch in policy.stages
    for new, previous, view in zip(plans.new_states, plans.states, plans.views, strict=True):
        stitch_after(new, previous, view, policy.stitch_steps, guided_only, policy.dynamics)
    return plans


class PhaseClock:
    """Wall time per phase of a cycle (a stage's ``phase``); CUDA is synchronised first."""

    def __init__(self, device: torch.device) -> None:
        self.device, self.timings = device, {}

    def tick(self, phase: str, start: float) -> float:
        """Add the time since ``start`` to ``phase``; returns now."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        now = time.perf_counter()
        self.timings[phase] = self.timings.get(phase, 0.0) + now - start
        return now


# The phase of each stage in a cycle's timings ("window" and "encoder" are encode's own; a
# method's own stages carry a ``phase`` attribute).
PHASE_OF = {
    rank: "ranking",
    generate: "generator",
    stitch: "generator",
    decode: "generator",
    avoid: "generator",
    stand: "generator",
}


def scene_maps(policy: PipelinePolicy, views: Sequence[SceneView]) -> DrivableMap | MapStack:
    """The scenes' maps for one lookup: their shared map, or a :class:`MapStack` in scene
    order, kept (shared with the policy's spawned copies) while it holds every map asked
    for."""
    maps = [view.map for view in views]
    if all(m is maps[0] for m in maps):
        return maps[0]
    stack = policy._maps.get("stack")
    if stack is None or not all(id(m) in stack.positions for m in maps):
        stack = prepare_maps(policy, maps)
    return stack.view([stack.positions[id(m)] for m in maps])


def prepare_maps(policy: PipelinePolicy, maps: Sequence[DrivableMap]) -> MapStack:
    """Stack ``maps`` (distinct ones, in order) for :func:`scene_maps` of ``policy`` and its
    spawned copies."""
    unique = list({id(m): m for m in maps}.values())
    stack = policy._maps.get("stack")
    if stack is None or [id(m) for m in stack.maps] != [id(m) for m in unique]:
        stack = MapStack(unique)
        policy._maps["stack"] = stack
    return stack


def plan_scenes(scenes: Sequence[PipelinePolicy], views: Sequence[SceneView]) -> None:
    """One planning cycle for B scenes: ``scenes[b]`` plans ``views[b]`` now.

    ``scenes`` are copies of one policy (:meth:`PipelinePolicy.spawn`, or the policy
    itself); ``scenes[0]`` runs the stages once for all of them, and each gets its new
    state, its buffer restarting at its ``view.step``. Every scene's ``timings`` are the
    cycle's: its phases (run once for all scenes) and its ``"total"``.

    Raises:
        ValueError: ``scenes`` and ``views`` differ in length or are empty, or the scenes
            are not distinct copies of one policy.
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
        if type(scene) is not type(planner) or scene._maps is not planner._maps:
            raise ValueError("scenes must be copies of one policy (PipelinePolicy.spawn)")
        if scene.state.episode < 0:
            raise RuntimeError("call reset(view) before plan(view)")
    if len({id(scene) for scene in scenes}) != len(scenes):
        raise ValueError("scenes must be distinct policy copies (one per scene)")
    previous_threads = torch.get_num_threads()
    if planner.threads is not None:
        torch.set_num_threads(planner.threads)
    try:
        start = time.perf_counter()
        planner.clock = PhaseClock(planner.device)
        states = [scene.state for scene in scenes]
        plans = PlanSet(views=views, states=states, drivable_map=scene_maps(planner, views))
        for stage in planner.stages:
            begin = time.perf_counter()
            with exact_scene_widths():  # a scene's network outputs are those it gets alone
                plans = stage(planner, plans)
            phase = PHASE_OF.get(stage, getattr(stage, "phase", None))
            if phase is not None:
                planner.clock.tick(phase, begin)
        total = time.perf_counter() - start
    finally:
        if planner.threads is not None:
            torch.set_num_threads(previous_threads)
    timings = dict(planner.clock.timings, total=total)
    for scene, view, state in zip(scenes, views, plans.new_states, strict=True):
        scene.state = state.replace(
            timings=dict(timings), plan_step=view.step, cycles=state.cycles + 1
        )


__all__ = [
    "PHASE_OF",
    "PhaseClock",
    "attacker_row",
    "avoid",
    "decode",
    "emit",
    "encode",
    "generate",
    "hold",
    "plan_scenes",
    "prepare_maps",
    "scene_maps",
    "rank",
    "restitch",
    "stand",
    "stand_still",
    "stitch",
    "world_plans",
]
