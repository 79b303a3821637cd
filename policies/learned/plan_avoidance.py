"""Avoidance steps: a few gradient steps that pull a joint base plan's boxes apart and
keep them on the road, before anything else uses the plan.

The one-step generator draws every agent's plan of a scene from one noise sample, and
the plans of neighbours overlap where the model's interaction is weak (without these
steps the shipped generator's vehicles collide far more often in closed loop:
docs/explanation/realism.md). Rule guidance of the sampler's output is how CTG (Zhong et al. 2023,
"Guided Conditional Diffusion for Controllable Traffic Simulation", ICRA) keeps its
traffic from colliding and leaving the road; here it is applied to the one-step output
``u`` (normalised action space) of every agent at once, with the same objective as the
best-of-M selection (:mod:`policies.learned.plan_overlap`) over its first
``OVERLAP_HORIZON`` steps:

    L(u) = sum_pairs relu(-separation)^2 + L_map,   u <- Adam(u, grad L),

the overlap summed over every pair of present agents that is apart now (the SAT
penetration depth, the simulator's own collision test) and ``L_map`` the guidance's map
term of every agent. The variables are the rows of the moving vehicles: the ego's row is
not one (the ego is not driven by the scene policy; the others avoid its predicted
plan), nor are absent rows, nor vehicles at rest (speed <= ``REST_SPEED``): they are
obstacles here, and whether they start is the generator's decision (and the holding
rule's, :mod:`policies.learned.plan_stitching`); as variables, the map term drove parked
cars that the map's raster shows off the road onto it (the real scenes); for the same
reason the map term forgives each variable what its footprint is off the road now
(:meth:`~policies.learned.guidance_losses.MapTerm.forgive`).

Each step costs what a guidance step does on the same rows (:mod:`policies.riskflow.guidance`):
the variables' rows are rolled out over the scored steps only, and every gradient is in
closed form, with no autograd graph: the map term's, the rollout's vector-Jacobian
product (``riskflow_env.dynamics.rollout_with_vjp``) and the overlap's
(:func:`~policies.learned.plan_overlap.overlap_gradient`, the SAT separation's
derivative, only for the pairs whose boxes can touch: a pair of variables, or a variable
and an obstacle).

The loop stops early when nothing is left to correct. When the first step's gradient is
exactly zero (no pair overlaps within the horizon, no footprint off the road beyond what
it forgives), every step would be zero (Adam's moments stay zero): the plans are those
of zero steps, bit for bit; about 60% of the unguided generator's one-scene calls stop
so. Later, the loop stops at a step whose gradient is exactly zero once the closest pair
of boxes is at least ``STOP_MARGIN`` (0.25 m) apart: after the last overlap is resolved,
Adam's momentum carries the plans a little further apart, and stopping as soon as the
gradient vanishes (no margin) tripled the unguided generator's non-ego collision scenes
in closed loop, while a 0.25 m margin keeps them near those of running every step at a
fraction of the steps. In a batched call each scene stops on
its own, as it would alone: its rows keep their correction from then on and leave the
loop (the later steps roll out and score only the scenes still going), and the loop ends
when every scene has stopped.

The guided adversaries leave out the pairs that guidance decides (``exempt``): a vehicle
of the controllable set ``A_c`` and one of its targets. Correcting them only pulled the
base plan that guidance starts from away from the target, a tug of war that cost steps
every cycle; the unguided generator (``k = 0``) has no such
pairs, and without ``L_adv`` (``lambda_adv = 0``) guidance pulls no pair together, so
every pair is corrected. ``steps = 0`` leaves the plans as they are; the MeanFlow
adversaries take ``DEFAULT_AVOID_STEPS`` (20) by default (20 steps leave half the
overlaps and centre off-road steps of 10).

**Braking fallback** (:func:`brake_to_clear`). The gradient of the penetration depth
points along the SAT axis of least overlap, which for a car closing on one ahead of it
but offset in its lane is sideways: the steps steer it past, the map term steers it back
onto the road, and the plan keeps running into the car ahead, cycle after cycle (an
unguided car struck a standing ego at 7.8 m/s that way, its plans overlapping the ego by
0.7-0.9 m for 2.5 s). After the steps, a variable whose plan still overlaps a scored
pair's box that is ahead of it at the first overlapping step brakes at the constant rate
that stops it ``BRAKE_MARGIN`` short of its last clear position (at most ``HUMAN_ACCEL``,
6 m/s^2, reached from its first action at ``BRAKE_JERK``), keeping its yaw rates: what a
driver does behind a car that is not getting out of the way. The guided vehicles do not
brake so: their plans are guidance's, whose separation term keeps them clear of the
others.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from policies.learned import compiled_plans
from policies.learned.adam import Adam
from policies.learned.data import Normalizer
from policies.learned.guidance_losses import HUMAN_ACCEL, MapTerm
from policies.learned.plan_overlap import (
    OVERLAP_HORIZON,
    overlap_gradient,
    pair_boxes,
    scored_pairs,
    touching_pairs,
)
from policies.learned.plan_stitching import REST_SPEED
from policies.learned.sampler import decode_plans
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, rollout, rollout_with_vjp
from riskflow_env.geometry import separation

DEFAULT_AVOID_STEPS = 20  # avoidance steps of the MeanFlow adversaries by default
BRAKE_MARGIN = 0.5
BRAKE_JERK = 20.0
"""[m/s^3] the braking fallback reaches its rate from the plan's first action at this
jerk (within the p99 of the data, 27.8 m/s^3, ``policies.stress.failures.HUMAN_BOUNDS``)"""
"""[m] a braking vehicle stops this far short of its last clear position (:func:`brake_to_clear`)"""
EGO_STANDS_BELOW = 2.0
"""[m/s] an ego slower than this is assumed to stay where it is (:func:`avoid_overlaps`)"""
STOP_MARGIN = 0.25
"""[m] the loop stops once no pair overlaps, every footprint is on the road and the
closest pair is this far apart (module docstring)"""


def avoid_overlaps(
    eps: Tensor,
    u0: Tensor,
    state: Tensor,
    length: Tensor,
    width: Tensor,
    agent_mask: Tensor,
    map_term_of: Callable[[Tensor], MapTerm | None] | None,
    normalizer: Normalizer,
    dynamics: DynamicsConfig,
    *,
    steps: int,
    step_size: float,
    ego: int = 0,
    horizon: int = OVERLAP_HORIZON,
    gain: Tensor | None = None,
    exempt: Tensor | None = None,
    brake: bool = True,
    guided: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Avoidance steps on the base plans of B scenes (module docstring).

    Args:
        eps: ``(B, A, T, 2)`` noise; ``u0`` the same shape, the base residual.
        state: ``(B, A, 4)`` current states (scene frame).
        length, width: ``(B, A)`` [m]; ``agent_mask`` ``(B, A)`` bool, present agents.
        map_term_of: ``rows -> MapTerm`` the map term of the given rows of the flattened
            ``B * A`` agents over ``horizon`` steps, or None (no map term).
        normalizer, dynamics: the plans' decoding (:func:`~policies.learned.sampler.decode_plans`;
            ``normalizer.denormalize`` affine, as for guidance).
        steps: Adam steps (0: ``u0`` unchanged); ``step_size`` its learning rate
            [normalised action units].
        ego: the ego's slot (not a variable; nor are vehicles at rest).
        horizon: plan steps in the objective.
        gain: ``(B, A, T, 1)`` the share of each step's correction that reaches the plan,
            or None (all of it). Blending first (:mod:`policies.learned.plan_stitching`)
            it is ``1 - blend_share(CORRECTION_STITCH_STEPS)`` on the first step of a
            vehicle with a plan to continue (one half), 1 elsewhere. The objective is
            scored on the plan with the gained correction.
        exempt: ``(B, A, A)`` bool, pairs whose overlap is not corrected, or None (every
            pair is). The guided adversaries leave out the pairs that guidance decides:
            a controllable vehicle and one of its targets (:func:`guided_pairs`).
        brake: after the steps, the variables whose plan still runs into a box ahead of
            them brake to stop short of it (:func:`brake_to_clear`; with ``steps > 0``).
        guided: ``(B, A)`` bool, the rows that guidance will bend (``A_c``), which do not
            brake (their plans are guidance's, and its separation term keeps them clear of
            the others), or None.

    Returns:
        ``(u, actions, trajectories)``: ``(B, A, T, 2)``, ``(B, A, T, 2)``, ``(B, A, T, 4)``.
    """
    variable = agent_mask & (state[..., SPEED] > REST_SPEED)
    variable[:, ego] = False
    rows = torch.nonzero(variable.flatten()).flatten()  # flat (scene, agent) indices
    variables = rows
    u = u0.detach().clone()
    # every row's plan, decoded once: only the variables' rows change below
    actions, trajectories = decode_plans(eps + u0, state, agent_mask, normalizer, dynamics)
    if steps > 0 and rows.numel() > 0:
        with torch.no_grad():
            # every row's plan over the scored steps; the variables' are replaced each step
            obstacles = trajectories[..., :horizon, :].clone()  # (B, A, H, 4)
            _assume_slow_ego_stands(obstacles, state, ego)
            # the pairs that can change: scored, with at least one variable
            pairs = scored_pairs(length, width, agent_mask, state)
            pairs = pairs & (variable[:, :, None] | variable[:, None, :])
            if exempt is not None:
                pairs = pairs & ~exempt
            scored = (pairs, length, width)  # the loop narrows them to the scenes still going
            moving = (eps + u0)[..., :horizon, :].flatten(0, 1)[rows]  # (V, H, 2)
            now = state.flatten(0, 1)[rows]
            term = None if map_term_of is None else map_term_of(rows)
            if term is not None:
                term.forgive(now)
            share = 1.0 if gain is None else gain[..., :horizon, :].flatten(0, 1)[rows]
            u_rows = u.flatten(0, 1)  # a view: the corrections are written through it
            if compiled_plans.accepts(moving, term, normalizer):  # the same loop, compiled
                u_rows[rows, :horizon] += compiled_plans.avoidance_correction(
                    rows, variable.shape[1], now, moving, share, obstacles, scored, term,
                    normalizer, dynamics, steps=steps, step_size=step_size,
                    stop_margin=STOP_MARGIN,
                )  # fmt: skip
            else:
                zero = torch.zeros_like(eps[0, 0, :1])  # (1, 2)
                scale = normalizer.denormalize(zero + 1.0) - normalizer.denormalize(zero)  # da/du
                delta = torch.zeros_like(moving)
                adam = Adam(delta, step_size)
                num_agents = variable.shape[1]
                # The loop's scenes are those not stopped yet: ``scene`` (the position of each
                # variable's scene among them) and ``slot`` index the compacted tensors.
                scene, slot = rows // num_agents, rows % num_agents
                for _ in range(steps):
                    planned, vjp = rollout_with_vjp(
                        now, normalizer.denormalize(moving + share * delta), dynamics
                    )
                    joint = obstacles.clone()
                    joint[scene, slot] = planned
                    d_joint, closest = overlap_gradient(
                        joint[:, None], length, width, pairs, STOP_MARGIN
                    )
                    d_planned = d_joint[:, 0][scene, slot]
                    if term is not None:
                        d_planned = d_planned + term.rows_and_gradient(planned)[1]
                    gradient = vjp(d_planned) * scale * share
                    # each scene stops on its own, as it would alone (module docstring)
                    keep = torch.zeros_like(closest[:, 0], dtype=torch.bool)  # left to correct
                    keep[scene[gradient.flatten(1).ne(0).any(dim=1)]] = True
                    if adam.count > 0:  # a later step: stop with a margin
                        keep |= closest[:, 0] < STOP_MARGIN
                    if not bool(keep.all()):
                        # the stopped scenes keep their correction; their rows leave the loop
                        going = keep[scene]
                        stopped = ~going
                        u_rows[rows[stopped], :horizon] += _rows(share, stopped) * delta[stopped]
                        if not bool(going.any()):
                            break
                        scene = (torch.cumsum(keep, 0) - 1)[scene[going]]
                        rows, slot, moving, now, delta, gradient = (
                            t[going] for t in (rows, slot, moving, now, delta, gradient)
                        )
                        share = _rows(share, going)
                        obstacles, length, width, pairs = (
                            t[keep] for t in (obstacles, length, width, pairs)
                        )
                        adam.select(going)
                        if term is not None:
                            term = map_term_of(rows)
                            term.forgive(now)
                    delta = delta - adam.step(gradient)
                else:
                    u_rows[rows, :horizon] += share * delta
        # the variables' rows decoded again (each row's decoding is its own)
        flat = [t.flatten(0, 1)[variables] for t in (eps, u, state, agent_mask)]
        decoded = decode_plans(flat[0] + flat[1], *flat[2:], normalizer, dynamics)
        for plan, new_rows in zip((actions, trajectories), decoded, strict=True):
            plan.view(-1, *plan.shape[2:])[variables] = new_rows
    if brake and steps > 0 and rows.numel() > 0:
        with torch.no_grad():
            may_brake = variable if guided is None else variable & ~guided.bool()
            predicted = trajectories[:, ego].clone()
            _assume_slow_ego_stands(trajectories, state, ego)
            braked = brake_to_clear(actions, trajectories, state, *scored, may_brake, dynamics)
            trajectories[:, ego] = predicted
            if braked.numel() > 0:  # their residual, as everywhere: denorm(eps + u) = actions
                flat = (eps.flatten(0, 1)[braked], actions.flatten(0, 1)[braked])
                u.view(-1, *u.shape[2:])[braked] = normalizer.normalize(flat[1]) - flat[0]
    return u, actions, trajectories


def _assume_slow_ego_stands(trajectories: Tensor, state: Tensor, ego: int) -> None:
    """In place: in the scenes whose ego is slower than ``EGO_STANDS_BELOW``, the ego's row
    of ``(B, A, H, 4)`` plans stands at its current pose (speed 0). The adversary does not
    know what the ego will do; its row is the generator's guess, and a follower that trusts
    a guess that the ego drives off runs into an ego that stays."""
    slow = state[:, ego, SPEED] < EGO_STANDS_BELOW  # (B,)
    if bool(slow.any()):
        standing = state[:, ego].clone()
        standing[:, SPEED] = 0.0
        rows = trajectories[:, ego]
        rows[slow] = standing[slow, None].expand_as(rows[slow])


def brake_to_clear(
    actions: Tensor,
    trajectories: Tensor,
    state: Tensor,
    pairs: Tensor,
    length: Tensor,
    width: Tensor,
    variable: Tensor,
    dynamics: DynamicsConfig,
    margin: float = BRAKE_MARGIN,
) -> Tensor:
    """In place: the variables whose plan still runs into a box ahead of them brake to
    stop short of it (module docstring).

    Over the plans' first ``H`` steps (``pairs``' horizon: the steps of ``trajectories``
    scored, up to ``OVERLAP_HORIZON``), a variable brakes when one of its ``pairs``
    overlaps and the other box's centre is ahead of it (along its heading) at the first
    overlapping step: from its plan's first action, its acceleration falls at
    ``BRAKE_JERK`` to a constant braking rate ``D`` and stays at most ``-D``, ``D`` the
    gentlest rate that stops it within ``d``, the distance its plan travels before that
    step less ``margin``, and at most ``HUMAN_ACCEL`` (a driver's hard braking; the
    dynamics allow more). The yaw rates are kept, and the row is rolled out again.

    Args:
        actions, trajectories: ``(B, A, T, 2)``, ``(B, A, T, 4)`` the plans.
        state: ``(B, A, 4)`` current states; ``length``, ``width`` ``(B, A)`` [m].
        pairs: ``(B, A, A)`` bool, the pairs the avoidance steps scored.
        variable: ``(B, A)`` bool, the rows that may brake.
        dynamics: the bounds and the rollout's time step.
        margin: [m] kept to the last clear position.

    Returns:
        ``(R,)`` the flat ``B * A`` indices of the rows that brake.
    """
    num_scenes, num_agents = variable.shape
    horizon = min(OVERLAP_HORIZON, trajectories.shape[2])
    near = trajectories[:, None, :, :horizon]  # (B, 1, A, H, 4): one joint plan per scene
    b, m, i, j = touching_pairs(near, length, width, pairs)
    gap = separation(*pair_boxes(near, length, width, b, m, i, j))  # (P, H)
    overlap = gap < 0
    hit = overlap.any(dim=-1)
    first = torch.argmax(overlap.to(torch.int8), dim=-1)  # (P,) first overlapping step
    stop_before = torch.full(
        (num_scenes * num_agents,), horizon, dtype=torch.long, device=variable.device
    )
    for me, other in ((i, j), (j, i)):
        own, theirs = near[b, 0, me, first], near[b, 0, other, first]  # (P, 4)
        heading = torch.stack([torch.cos(own[:, 3]), torch.sin(own[:, 3])], dim=-1)
        ahead = ((theirs[:, :2] - own[:, :2]) * heading).sum(dim=-1) > 0
        brake = hit & ahead & variable[b, me]
        stop_before = stop_before.scatter_reduce(
            0, (b * num_agents + me)[brake], first[brake], reduce="amin"
        )
    rows = torch.nonzero(stop_before < horizon).flatten()
    if rows.numel() == 0:
        return rows
    now = state.flatten(0, 1)[rows]
    xy = torch.cat([now[:, None, :2], trajectories.flatten(0, 1)[rows, :, :2]], dim=1)
    steps = torch.linalg.vector_norm(xy[:, 1:] - xy[:, :-1], dim=-1)  # (R, T)
    travelled = torch.cat([steps.new_zeros(steps.shape[0], 1), steps.cumsum(dim=1)], dim=1)
    clear = travelled.gather(1, stop_before[rows, None])[:, 0] - margin
    speed = now[:, SPEED]
    braked = actions.flatten(0, 1)[rows]
    braked[..., 0] = torch.minimum(braked[..., 0], _braking(braked[..., 0], speed, clear, dynamics))
    flat = num_scenes * num_agents
    actions.view(flat, *actions.shape[2:])[rows] = braked
    trajectories.view(flat, *trajectories.shape[2:])[rows] = rollout(now, braked, dynamics)
    return rows


def _rows(share: Tensor | float, index: Tensor) -> Tensor | float:
    """The rows ``index`` of a per-row ``share``, or the scalar share itself."""
    return share[index] if isinstance(share, Tensor) else share


def _braking(accel: Tensor, speed: Tensor, clear: Tensor, dynamics: DynamicsConfig) -> Tensor:
    """``(R, T)`` the braking profile of :func:`brake_to_clear`: from the plan's first
    acceleration down at ``BRAKE_JERK`` to ``-D``, ``D`` the gentlest rate on a 0.05 m/s^2
    grid up to ``HUMAN_ACCEL`` whose stop (the rollout's speed bound at 0, trapezoidal
    steps) lies within ``clear`` [m]; the strongest where none does. ``accel`` ``(R, T)``
    the plans' accelerations, ``speed`` ``(R,)`` the current speeds. A 1-D estimate that
    picks the rate; the braked plan itself is rolled out by ``dynamics.rollout``."""
    strongest = min(-dynamics.accel_min, HUMAN_ACCEL)
    rates = torch.arange(0.0, strongest + 1e-9, 0.05, dtype=accel.dtype, device=accel.device)
    steps = torch.arange(accel.shape[1], dtype=accel.dtype, device=accel.device)
    ramp = accel[:, :1] - BRAKE_JERK * dynamics.dt * steps  # (R, T)
    profile = torch.minimum(accel[:, None], torch.maximum(ramp[:, None], -rates[:, None]))
    speeds = torch.clamp(speed[:, None, None] + dynamics.dt * profile.cumsum(dim=-1), min=0)
    before = torch.cat([speed[:, None, None].expand(-1, rates.numel(), 1), speeds[..., :-1]], -1)
    travel = (0.5 * (before + speeds) * dynamics.dt).sum(dim=-1)  # (R, G) [m]
    stops = travel <= clear[:, None]
    pick = torch.where(stops.any(dim=1), torch.argmax(stops.to(torch.int8), dim=1), -1)
    return torch.maximum(ramp, -rates[pick][:, None])


def guided_pairs(controllable: Tensor, targets: Tensor) -> Tensor:
    """``(B, A, A)`` bool: the pairs of a controllable vehicle and one of its targets,
    either way round (``controllable``, ``targets``: ``(B, A)`` bool), the ``exempt`` of
    :func:`avoid_overlaps` for the guided adversaries."""
    pairs = controllable[:, :, None] & targets[:, None, :]
    return pairs | pairs.transpose(1, 2)


__all__ = [
    "BRAKE_JERK",
    "BRAKE_MARGIN",
    "DEFAULT_AVOID_STEPS",
    "STOP_MARGIN",
    "avoid_overlaps",
    "brake_to_clear",
    "guided_pairs",
]
