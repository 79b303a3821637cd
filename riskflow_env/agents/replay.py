"""Log replay: vehicles follow the scenario's reference future (recorded or synthesised).

Two modes, both vectorised over agents:

* ``"open_loop"``: pure inverse dynamics (:func:`riskflow_env.dynamics.inverse`) of the
  reference: ``accel = dv / dt`` and ``yaw_rate = wrap(dpsi) / dt`` from consecutive
  reference states. It reproduces the logged speeds and headings exactly, and the
  positions only as far as the log follows the unicycle model (it drifts where the
  logged heading is not the direction of motion, or on curves sampled at 10 Hz).
* ``"tracking"`` (default): inverse dynamics with position feedback, so that the
  simulated vehicle stays on the logged positions. Each step the speed after the step
  is chosen so that, held constant, it covers the along-track distance to the
  reference position ``SPEED_PREVIEW`` steps ahead (a short preview spreads the speed
  steps of keyframe-interpolated logs, e.g. nuScenes, over a few steps and keeps the
  errors decaying without ringing; the next position when the log ends sooner), and
  the yaw rate turns
  the heading toward the first reference position at least ``AIM_DISTANCE`` ahead
  (two or more steps on) of where the vehicle will be. Where there is none within
  ``AIM_STEPS`` (slow or stopped vehicles), the yaw rate tracks the reference heading
  instead. Actions are clipped to the dynamics bounds. A unicycle neither slides
  sideways nor reverses, so the jitter of near-stationary annotated vehicles is not
  reproduced.

Gaps inside a reference (invalid steps between valid ones) are bridged by linear
interpolation (heading along the shortest arc). Where a vehicle's reference has ended
(no valid step left), it holds its speed and heading: zero acceleration and yaw rate.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from riskflow_env.agents.base import actions_dict, controlled_mask
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, YAW, inverse, wrap_angle
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.view import SceneView

ReplayMode = Literal["tracking", "open_loop"]
REPLAY_MODES: tuple[ReplayMode, ...] = ("tracking", "open_loop")
AIM_DISTANCE = 1.0  # [m] closer reference points give no reliable direction to aim at
SPEED_PREVIEW = 3  # [steps] reference step whose position the speed aims to reach
AIM_STEPS = 10  # reference steps searched for an aim point


class ReplayPolicy:
    """Replays the reference future of every controlled vehicle (see the module docstring).

    Args:
        controlled: ``"others"`` (every vehicle but the ego), ``"all"``, or agent names.
        mode: ``"tracking"`` (position feedback) or ``"open_loop"`` (inverse dynamics).
        dynamics: the env's dynamics (time step and bounds).
    """

    def __init__(
        self,
        controlled: str | Sequence[str] = "others",
        mode: ReplayMode = "tracking",
        dynamics: DynamicsConfig | None = None,
    ) -> None:
        if mode not in REPLAY_MODES:
            raise ValueError(f"mode must be 'tracking' or 'open_loop', got {mode!r}")
        self.controlled = controlled
        self.mode = mode
        self.dynamics = dynamics or DynamicsConfig()
        self._scenario: Scenario | None = None
        self._reference = np.zeros((0, 0, 4))
        self._valid = np.zeros((0, 0), dtype=bool)
        self._start_step = 0

    def reset(self, view: SceneView) -> None:
        """Take each slot's reference track, from the current step on.

        The reference of slot ``i`` is ``view.scenario.states[view.scenario_rows[i]]``
        from ``scenario.current_index`` to the end, each step valid where the scenario
        says so; empty slots have none.
        """
        scenario, rows = view.scenario, np.asarray(view.scenario_rows)
        if abs(scenario.dt - self.dynamics.dt) > 1e-9:
            raise ValueError(
                f"ReplayPolicy: scenario dt {scenario.dt} s differs from the dynamics dt "
                f"{self.dynamics.dt} s"
            )
        future = scenario.states[:, scenario.current_index :]
        future_valid = scenario.valid[:, scenario.current_index :]
        has_row = rows >= 0
        self._reference = np.zeros((view.num_agents,) + future.shape[1:])
        self._valid = np.zeros((view.num_agents, future.shape[1]), dtype=bool)
        self._reference[has_row] = future[rows[has_row]]
        self._valid[has_row] = future_valid[rows[has_row]]
        self._reference, self._valid = _bridge_gaps(self._reference, self._valid)
        self._scenario = scenario
        self._start_step = view.step

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """``{agent: (accel [m/s^2], yaw_rate [rad/s])}`` for the controlled live agents."""
        if view.scenario is not self._scenario or view.step < self._start_step:
            self.reset(view)
        mask = controlled_mask(view, self.controlled)
        rows = np.flatnonzero(mask)
        actions = np.zeros((view.num_agents, 2))
        if rows.size:
            actions[rows] = self._actions(view.current[rows], rows, view.step - self._start_step)
        return actions_dict(view, mask, actions)

    def _actions(self, state: np.ndarray, rows: np.ndarray, elapsed: int) -> np.ndarray:
        """(n, 2) actions of slots ``rows`` in ``state`` (n, 4), ``elapsed`` steps in."""
        dyn = self.dynamics
        steps = self._reference.shape[1]
        index = np.minimum(elapsed + np.arange(3), steps - 1)  # now, next, after next
        in_log = elapsed + np.arange(3) < steps
        reference = self._reference[rows][:, index]  # (n, 3, 4)
        valid = self._valid[rows][:, index] & in_log  # (n, 3)
        live = valid[:, 1]
        if self.mode == "open_loop":
            actions = inverse(reference[:, :2], dyn)[:, 0]
            return np.where((live & valid[:, 0])[:, None], actions, 0.0)

        speed, yaw = state[:, SPEED], state[:, YAW]
        heading = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
        # constant speed v' after this step covers (v + v') dt / 2 + (m - 1) v' dt = along
        m = SPEED_PREVIEW
        preview = np.minimum(elapsed + m, steps - 1)
        use_preview = (elapsed + m < steps) & self._valid[rows, preview]
        m = np.where(use_preview, m, 1)
        goal = np.where(
            use_preview[:, None], self._reference[rows, preview, :2], reference[:, 1, :2]
        )
        along = np.sum((goal - state[:, :2]) * heading, axis=-1)
        next_speed = np.where(m > 1, (along / dyn.dt - 0.5 * speed) / (m - 0.5), along / dyn.dt)
        next_speed = np.clip(next_speed, dyn.speed_min, dyn.speed_max)
        accel = (next_speed - speed) / dyn.dt
        predicted = state[:, :2] + heading * (0.5 * (speed + next_speed) * dyn.dt)[:, None]
        window = np.minimum(elapsed + 2 + np.arange(AIM_STEPS), steps - 1)
        ahead_ok = self._valid[rows][:, window] & (elapsed + 2 + np.arange(AIM_STEPS) < steps)
        aim = self._reference[rows][:, window, :2] - predicted[:, None]  # (n, W, 2)
        far = ahead_ok & (np.linalg.norm(aim, axis=-1) >= AIM_DISTANCE)
        first = np.argmax(far, axis=-1)
        aim = aim[np.arange(len(rows)), first]
        aim_heading = np.arctan2(aim[:, 1], aim[:, 0])
        forward = np.cos(aim_heading - reference[:, 1, YAW]) > 0  # not behind the vehicle
        target = np.where(far.any(axis=-1) & forward, aim_heading, reference[:, 1, YAW])
        yaw_rate = wrap_angle(target - yaw) / dyn.dt
        accel = np.clip(accel, dyn.accel_min, dyn.accel_max)
        yaw_rate = np.clip(yaw_rate, -dyn.yaw_rate_max, dyn.yaw_rate_max)
        return np.where(live[:, None], np.stack([accel, yaw_rate], axis=-1), 0.0)


def _bridge_gaps(reference: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill invalid steps lying between valid ones by interpolation.

    Args:
        reference: (A, T, 4) tracks; valid: (A, T) bool.

    Returns:
        (A, T, 4) tracks and (A, T) validity with interior gaps filled and valid.
    """
    steps = np.arange(valid.shape[1])
    before = np.maximum.accumulate(np.where(valid, steps, -1), axis=1)
    after = np.minimum.accumulate(np.where(valid, steps, steps.size)[:, ::-1], axis=1)[:, ::-1]
    gap = ~valid & (before >= 0) & (after < steps.size)
    if not gap.any():
        return reference, valid
    low, high = np.maximum(before, 0), np.minimum(after, steps.size - 1)
    fraction = np.where(gap, (steps - low) / np.maximum(high - low, 1), 0.0)[..., None]
    start = np.take_along_axis(reference, low[..., None], axis=1)
    end = np.take_along_axis(reference, high[..., None], axis=1)
    filled = start + fraction * (end - start)
    filled[..., YAW] = start[..., YAW] + fraction[..., 0] * wrap_angle(
        end[..., YAW] - start[..., YAW]
    )
    return np.where(gap[..., None], filled, reference), valid | gap
