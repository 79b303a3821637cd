"""Plan stitching: a new plan of a plan-buffer policy continues the one being executed.

A re-plan does not switch the actions at once. The first ``stitch_steps`` actions of the
new plan (5 = 0.5 s by default) are blended with the continuation of the plan being
executed, the previous plan's share falling linearly (``n/(n+1), ..., 1/(n+1)``), and the
plan is rolled out again from the current state. Positions and speeds are continuous
across a re-plan anyway (every plan starts at the current state); this makes the
acceleration and yaw rate continuous too, which removes the jerk spike at every re-plan
(the step that switched plans had about twice the p95 jerk of the steps within a plan).
``AdversaryConfig.stitch_steps`` sets the length (``DEFAULT_STITCH_STEPS`` by default; 0
switches at once). A blend longer than the planning interval reaches into the next
re-plan's blend, so each executed action is a weighted mean of the last few plans; it
damps the generator's plan-to-plan noise (docs/REALISM.md, round 11).

**Smoothing** (``AdversaryConfig.smooth_steps``, off by default). The one-step
generator's plans carry step-to-step noise in the acceleration that the data does not
have: it is most of the generated traffic's KDD (the Wasserstein distance of its jerk to
the log's, 1.4 m/s^3 against 0.4 for IDM traffic). A centred moving average of
``smooth_steps`` steps over each new plan's accelerations (the ends held) removes it
before the plan is rolled out again; the yaw rates are left as they are.

**Holding at rest** (``AdversaryConfig.hold_distance``, ``DEFAULT_HOLD_DISTANCE`` = 4 m by
default; 0 turns it off). A vehicle at rest
(speed <= ``REST_SPEED``) whose new plan moves it less than ``hold_distance`` [m] over the
whole horizon keeps its brake on: the plan's positive accelerations are dropped and its
yaw rate set to 0, so it stays where it is. The reason is the speed bound at 0: the
generator's plans for a standing vehicle carry zero-mean acceleration noise (about 0.2-0.3
m/s^2 per step on the real scenes), which the bound rectifies into forward motion, and the
yaw rate turns a unicycle in place; re-planned every 0.5 s, parked cars creep 1-3 m and
touch their neighbours in rows of parked cars. A plan that moves the vehicle by more than
``hold_distance`` (a start from a queue) runs as it is. docs/REALISM.md, rounds 8 and 9,
has the measurements (at 4 m, 97% of the real samples' parked cars stay within 2 m).

:class:`PlanStitching` is a mixin of :class:`~policies.learned.plan_buffer.PlanBufferPolicy`
(``plan_scenes`` calls :meth:`PlanStitching._shape`, smoothing then holding at rest,
and :meth:`PlanStitching._stitch` on every scene that planned).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d

from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, inverse, rollout
from riskflow_env.view import SceneView

REST_SPEED = 0.2  # [m/s] a vehicle at or below this speed is at rest (holding at rest)
DEFAULT_HOLD_DISTANCE = 4.0  # [m] the adversaries' default holding distance (module docstring)
DEFAULT_STITCH_STEPS = 5  # [steps] the adversaries' default re-plan blend (module docstring)


class PlanStitching:
    """Blends new plans into the executed ones and holds vehicles at rest (module
    docstring).

    Works on the policy's stored plans: ``plan_actions`` (A, T, 2), ``plans`` and
    ``base_plans`` (A, T, 4), ``plan_mask`` and ``controllable`` (A,), with its
    ``dynamics`` and ``hold_distance``.
    """

    stitch_steps: int = DEFAULT_STITCH_STEPS  # [steps] re-plan blend; 0: switch at once
    hold_distance: float = 0.0  # [m] holding at rest (module docstring); 0: off
    smooth_steps: int = 1  # [steps] moving average of the accelerations; 1: off
    dynamics: DynamicsConfig
    plan_actions: np.ndarray
    plans: np.ndarray | None
    base_plans: np.ndarray | None
    plan_mask: np.ndarray
    controllable: np.ndarray

    def _shape(self, view: SceneView) -> None:
        """Smooth the new plans, then hold vehicles at rest (module docstring)."""
        self._smooth(view)
        self._hold_at_rest(view)

    def _smooth(self, view: SceneView) -> None:
        """Centred moving average of ``smooth_steps`` over the new plans' accelerations
        (module docstring); the plans are rolled out again."""
        if self.smooth_steps <= 1:
            return
        rows = np.flatnonzero(self.plan_mask & view.active)
        if rows.size == 0:
            return
        smooth = self.plan_actions[rows]
        smooth[..., 0] = uniform_filter1d(smooth[..., 0], self.smooth_steps, axis=1, mode="nearest")
        self._replace_plans(view, rows, smooth)

    def _hold_at_rest(self, view: SceneView) -> None:
        """Keep the brake on for vehicles at rest whose new plan hardly moves them
        (module docstring); their plans are rolled out again. Guided vehicles are held
        alike; their unguided alternative (``base_plans``) is left as it is."""
        if self.hold_distance <= 0.0:
            return
        current = view.current
        rows = np.flatnonzero(self.plan_mask & view.active & (current[:, SPEED] <= REST_SPEED))
        if rows.size == 0:
            return
        reach = np.linalg.norm(self.plans[rows, :, :2] - current[rows, None, :2], axis=-1)
        rows = rows[reach.max(axis=1) < self.hold_distance]
        if rows.size == 0:
            return
        held = self.plan_actions[rows]
        held[..., 0] = np.minimum(held[..., 0], 0.0)
        held[..., 1] = 0.0
        self._replace_plans(view, rows, held)

    def _replace_plans(self, view: SceneView, rows: np.ndarray, actions: np.ndarray) -> None:
        """New actions (R, T, 2) for the plans of ``rows``, rolled out from the current
        states; the unguided rows' alternative (``base_plans``) is the same plan, the
        guided rows' is left as it is."""
        self.plan_actions[rows] = actions
        self.plans[rows] = rollout(view.current[rows], actions, self.dynamics)
        unguided = rows[~self.controllable[rows]]
        self.base_plans[unguided] = self.plans[unguided]

    def _stitch(self, view: SceneView, actions: np.ndarray, mask: np.ndarray, elapsed: int) -> None:
        """Blend the first ``stitch_steps`` actions of the new plans with the rest of the
        previous plans (module docstring) and roll the plans out again.

        Args: the previous ``plan_actions`` (A, T, 2) and ``plan_mask`` (A,), and the
        steps executed of them (``elapsed``).
        """
        steps = min(self.stitch_steps, actions.shape[1] - elapsed, self.plan_actions.shape[1])
        same = mask.shape == self.plan_mask.shape
        rows = np.flatnonzero(self.plan_mask & mask & view.active) if same else []
        if steps <= 0 or len(rows) == 0:
            return
        keep = (1.0 - np.arange(1, steps + 1) / (steps + 1))[:, None]  # previous plan's share
        old = actions[rows, elapsed : elapsed + steps]

        def blend(plan_actions: np.ndarray, previous: np.ndarray) -> np.ndarray:
            plan_actions[:, :steps] = keep * previous + (1.0 - keep) * plan_actions[:, :steps]
            return plan_actions

        current = view.current[rows]
        self.plan_actions[rows] = blend(self.plan_actions[rows], old)
        self.plans[rows] = rollout(current, self.plan_actions[rows], self.dynamics)
        # The unguided alternative is stitched alike: the same plans where nothing was
        # guided; for A_c its own actions (inverse dynamics of the base plan), blended.
        guided = self.controllable[rows]
        self.base_plans[rows[~guided]] = self.plans[rows[~guided]]
        if guided.any():
            start = current[guided][:, None]
            base = inverse(np.concatenate([start, self.base_plans[rows[guided]]], axis=1))
            base = blend(base, old[guided])
            self.base_plans[rows[guided]] = rollout(current[guided], base, self.dynamics)


__all__ = ["REST_SPEED", "PlanStitching"]
