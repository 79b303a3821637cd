"""Plan stitching: a new plan of a plan-buffer policy continues the one being executed.

A re-plan does not switch the actions at once. The first ``stitch_steps`` actions of the
new plan (5 = 0.5 s by default) are blended with the continuation of the plan being
executed, the previous plan's share falling linearly (``n/(n+1), ..., 1/(n+1)``), and the
plan is rolled out again from the current state. Positions and speeds are continuous
across a re-plan anyway (every plan starts at the current state); this makes the
acceleration and yaw rate continuous too, which removes the jerk spike at every re-plan
(the step that switched plans had about twice the p95 jerk of the steps within a plan).
Set ``policy.stitch_steps = 0`` to switch at once.

:class:`PlanStitching` is a mixin of :class:`~policies.learned.plan_buffer.PlanBufferPolicy`
(``plan_scenes`` calls :meth:`PlanStitching._stitch` on every scene that had a plan).
"""

from __future__ import annotations

import numpy as np

from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import inverse, rollout
from riskflow_env.view import SceneView


class PlanStitching:
    """Blends new plans into the executed ones (module docstring).

    Works on the policy's stored plans: ``plan_actions`` (A, T, 2), ``plans`` and
    ``base_plans`` (A, T, 4), ``plan_mask`` and ``controllable`` (A,), with its
    ``dynamics``.
    """

    stitch_steps: int = 5  # [steps] re-plan blend (module docstring); 0: switch at once
    dynamics: DynamicsConfig
    plan_actions: np.ndarray
    plans: np.ndarray | None
    base_plans: np.ndarray | None
    plan_mask: np.ndarray
    controllable: np.ndarray

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


__all__ = ["PlanStitching"]
