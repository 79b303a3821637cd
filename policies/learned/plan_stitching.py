"""Plan stitching: a new plan of a plan-buffer policy continues the one being executed.

A re-plan does not switch the actions at once. The first ``stitch_steps`` actions of the
new plan are blended with the continuation of the plan being executed, the previous
plan's share falling linearly (``n/(n+1), ..., 1/(n+1)``), and the plan is rolled out
again from the current state. Positions and speeds are continuous across a re-plan anyway
(every plan starts at the current state); this makes the acceleration and yaw rate
continuous too, which removes the jerk spike at every re-plan (the step that switched
plans had about twice the p95 jerk of the steps within a plan).
``AdversaryConfig.stitch_steps`` sets the length (None, the default: 15 steps = 1.5 s
blending first, 5 blending after planning; 0 switches at once). A blend longer than the
planning interval reaches into the next re-plan's blend, so each executed action is a
weighted mean of the last few plans; it damps the generator's plan-to-plan noise.

**Blending first** (the MeanFlow adversaries:
``RiskFlowAdversary``, ``NominalGenerator`` and STRIVE-style, whatever their generator,
over ``DEFAULT_FIRST_STITCH_STEPS`` = 15 steps). Blended after planning, a long
blend delays every correction that planning made, the avoidance steps' too, and costs
off-road steps and collisions. Blending first, the MeanFlow adversaries blend each new
*base* plan into the executed one before the avoidance steps
(:func:`continuation` gives the executed plans' continuation and weights),
so the avoidance steps correct the plan that will run; their corrections are blended
too, over ``CORRECTION_STITCH_STEPS`` (1: half of the first action's correction), which
removes the jerk spike that unblended corrections leave at the re-plan step (longer
correction blends delay the avoidance and cost off-road steps); after planning only the
guided rows are blended (guidance changed them after the blend).
``AdversaryConfig.stitch_steps=None`` (the default) resolves to 15 steps blending first
and to ``DEFAULT_STITCH_STEPS`` (5) blending after planning (the diffusion baselines, the
raw base).

**Holding at rest** (``AdversaryConfig.hold_distance``, ``DEFAULT_HOLD_DISTANCE`` = 4 m by
default; 0 turns it off). A vehicle at rest
(speed <= ``REST_SPEED``) whose new plan moves it less than ``hold_distance`` [m] over the
whole horizon keeps its brake on: the plan's positive accelerations are dropped and its
yaw rate set to 0, so it stays where it is. The reason is the speed bound at 0: the
generator's plans for a standing vehicle carry zero-mean acceleration noise (about 0.2-0.3
m/s^2 per step on the real scenes), which the bound rectifies into forward motion (and a
creeping car may turn: ``DynamicsConfig.turn_radius_min``); re-planned every 0.5 s, parked
cars creep 1-3 m and touch their neighbours in rows of parked cars. A plan that moves the
vehicle by more than ``hold_distance`` (a start from a queue) runs as it is. At 4 m, 97% of
the real samples' parked cars stay within 2 m.

The ``stitch``, ``hold`` and ``restitch`` stages of :mod:`policies.pipeline.stages` call
:func:`blend_first` (all scenes at once), :func:`hold_at_rest` and :func:`stitch_after`
(each scene that planned).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from policies.learned.data import Normalizer
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, rollout
from riskflow_env.view import SceneView

PlannerState = Any  # policies.pipeline.state.PlannerState (the pipeline layer sits above)

REST_SPEED = 0.2  # [m/s] a vehicle at or below this speed is at rest (holding at rest)
DEFAULT_HOLD_DISTANCE = 4.0  # [m] the adversaries' default holding distance (module docstring)
DEFAULT_STITCH_STEPS = 5  # [steps] the default re-plan blend after planning (module docstring)
DEFAULT_FIRST_STITCH_STEPS = 15  # [steps] the default blend when blending first
CORRECTION_STITCH_STEPS = 1  # [steps] blend of the avoidance corrections, blending first


def resolve_stitch_steps(stitch_steps: int | None, blends_first: bool) -> int:
    """The re-plan blend [steps] of ``AdversaryConfig.stitch_steps``: the given length, or
    for None 15 steps for a policy that blends first and 5 for one that blends after
    planning (module docstring)."""
    if stitch_steps is not None:
        return int(stitch_steps)
    return DEFAULT_FIRST_STITCH_STEPS if blends_first else DEFAULT_STITCH_STEPS


def replace_plans(
    state: PlannerState, view: SceneView, rows: np.ndarray, actions: np.ndarray, dynamics
) -> None:
    """In place: new actions (R, T, 2) for the plans of ``rows`` of ``state``, rolled out
    from the current states; the unguided rows' alternative (``base_plans``) is the same
    plan, the guided rows' is left as it is."""
    state.plan_actions[rows] = actions
    state.plans[rows] = rollout(view.current[rows], actions, dynamics)
    unguided = rows[~state.controllable[rows]]
    state.base_plans[unguided] = state.plans[unguided]
    state.base_actions[unguided] = actions[~state.controllable[rows]]


def hold_at_rest(
    state: PlannerState, view: SceneView, hold_distance: float, dynamics: DynamicsConfig
) -> None:
    """In place: keep the brake on for vehicles at rest whose new plan hardly moves them
    (module docstring); their plans are rolled out again. Guided vehicles are held alike;
    their unguided alternative (``base_plans``) is left as it is."""
    current = view.current
    rows = np.flatnonzero(state.plan_mask & view.active & (current[:, SPEED] <= REST_SPEED))
    if rows.size == 0:
        return
    reach = np.linalg.norm(state.plans[rows, :, :2] - current[rows, None, :2], axis=-1)
    rows = rows[reach.max(axis=1) < hold_distance]
    if rows.size == 0:
        return
    held = state.plan_actions[rows]
    held[..., 0] = np.minimum(held[..., 0], 0.0)
    held[..., 1] = 0.0
    replace_plans(state, view, rows, held, dynamics)


def continuation(
    state: PlannerState, view: SceneView, slots: np.ndarray, steps: int, stitch_steps: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """What the blend of a new plan of ``steps`` steps needs, before planning (blending
    first, module docstring): the executed plans' actions from now on ``(S, n, 2)`` for the
    env ``slots`` and the previous plan's share ``(S, n)`` (0 for slots without a plan to
    continue); None when nothing is blended."""
    if state.plan_step is None or stitch_steps <= 0:
        return None
    if slots.size and slots.max() >= state.plan_mask.shape[0]:  # not the planned slots
        return None
    elapsed = view.step - state.plan_step
    n = min(stitch_steps, state.plan_actions.shape[1] - elapsed, steps)
    if n <= 0:
        return None
    old = state.plan_actions[slots, elapsed : elapsed + n]
    live = state.plan_mask[slots] & view.active[slots]
    share = np.where(live[:, None], blend_share(n)[None], 0.0)
    return old, share


def blend_first(
    states: Sequence[PlannerState],
    views: Sequence[SceneView],
    slots: Sequence[np.ndarray],
    eps: torch.Tensor,
    u0: torch.Tensor,
    normalizer: Normalizer,
    stitch_steps: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Blending first (module docstring), for B scenes planned together: each new base plan
    ``denorm(eps + u0)`` blended into the :func:`continuation` of the plan its scene is
    executing.

    Args:
        states, views: each scene's planner state (before this cycle) and view.
        slots: each scene's env slot of every window row.
        eps, u0: ``(B, A, T, 2)`` the noise and the base residual (normalised).
        normalizer: the actions' normalisation.
        stitch_steps: the blend's length.

    Returns:
        ``(u, gain)``: ``(B, A, T, 2)`` the residual whose plans start with the blend, and
        ``(B, A, T, 1)`` the share of an avoidance correction that reaches each step (the
        corrections are blended over ``CORRECTION_STITCH_STEPS``).
    """
    old, share = torch.zeros_like(u0), torch.zeros_like(u0[..., :1])
    for index, (state, view) in enumerate(zip(states, views, strict=True)):
        blend = continuation(state, view, slots[index], u0.shape[2], stitch_steps)
        if blend is not None:
            previous, weight = (torch.as_tensor(x, dtype=u0.dtype) for x in blend)
            rows, steps = slice(0, len(slots[index])), weight.shape[1]
            old[index, rows, :steps] = previous.to(u0.device)
            share[index, rows, :steps, 0] = weight.to(u0.device)
    with torch.no_grad():
        actions = normalizer.denormalize(eps + u0)
        blended = normalizer.normalize(share * old + (1 - share) * actions) - eps
    steps = min(CORRECTION_STITCH_STEPS, share.shape[2])
    gain = torch.ones_like(share)
    gain[:, :, :steps] -= torch.where(
        share[:, :, :steps] > 0, share.new_tensor(blend_share(steps))[:, None], 0.0
    )
    return blended, gain


def stitch_after(
    state: PlannerState,
    previous: PlannerState,
    view: SceneView,
    stitch_steps: int,
    guided_only: bool,
    dynamics: DynamicsConfig,
) -> None:
    """In place: blend the first ``stitch_steps`` actions of ``state``'s new plans with the
    rest of ``previous``'s plans (module docstring) and roll the plans out again; with
    ``guided_only`` the guided rows only (the others were blended first)."""
    if previous.plan_step is None or stitch_steps <= 0:
        return
    actions, mask = previous.plan_actions, previous.plan_mask
    elapsed = view.step - previous.plan_step
    steps = min(stitch_steps, actions.shape[1] - elapsed, state.plan_actions.shape[1])
    same = mask.shape == state.plan_mask.shape
    chosen = state.plan_mask & (state.controllable if guided_only else True)
    rows = np.flatnonzero(chosen & mask & view.active) if same else []
    if steps <= 0 or len(rows) == 0:
        return
    keep = blend_share(steps)[:, None]  # previous plan's share
    old = actions[rows, elapsed : elapsed + steps]

    def blend(plan_actions: np.ndarray, executed: np.ndarray) -> np.ndarray:
        plan_actions[:, :steps] = keep * executed + (1.0 - keep) * plan_actions[:, :steps]
        return plan_actions

    current = view.current[rows]
    state.plan_actions[rows] = blend(state.plan_actions[rows], old)
    state.plans[rows] = rollout(current, state.plan_actions[rows], dynamics)
    # The unguided alternative is stitched alike: the same plans where nothing was
    # guided; for A_c its own actions, blended.
    guided = state.controllable[rows]
    state.base_plans[rows[~guided]] = state.plans[rows[~guided]]
    state.base_actions[rows[~guided]] = state.plan_actions[rows[~guided]]
    if guided.any():
        base = blend(state.base_actions[rows[guided]], old[guided])
        state.base_actions[rows[guided]] = base
        state.base_plans[rows[guided]] = rollout(current[guided], base, dynamics)


def blend_share(steps: int) -> np.ndarray:
    """(steps,) the executed plan's share in a blend of ``steps`` steps:
    ``steps/(steps+1), ..., 1/(steps+1)`` (module docstring)."""
    return 1.0 - np.arange(1, steps + 1) / (steps + 1)


__all__ = [
    "CORRECTION_STITCH_STEPS",
    "DEFAULT_FIRST_STITCH_STEPS",
    "DEFAULT_STITCH_STEPS",
    "REST_SPEED",
    "blend_share",
    "continuation",
    "hold_at_rest",
    "replace_plans",
    "stitch_after",
    "resolve_stitch_steps",
]
