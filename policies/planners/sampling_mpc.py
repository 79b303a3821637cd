"""Sampling MPC ego planner, with constant-velocity predictions or the adversary's plans.

Every step it rolls out a fixed set of candidate action sequences with the env's own
dynamics (:func:`riskflow_env.dynamics.rollout`, one call for all candidates), scores
each against the other vehicles' *predicted* boxes and the map, and applies the first
action of the cheapest (receding horizon). The prediction is what distinguishes the two
planners:

* :class:`SamplingMPCPlanner` predicts that every other vehicle keeps its current speed
  and heading (:class:`ConstantVelocityPrediction`): an ordinary planner, which sees no
  more than the current states of the other vehicles;
* :class:`OraclePlanner` reads what the adversary intends to do
  (:meth:`~policies.pipeline.policy.PipelinePolicy.predicted_states`), which no
  real ego can see. It answers whether the collisions the adversary sets up are
  avoidable at all.

A candidate holds an acceleration over the whole horizon and a yaw rate for ``d`` steps
followed by the opposite yaw rate for ``d`` steps (a lane-change shape; ``d`` = the
horizon gives a constant turn). Its cost, with per-step discount ``gamma``:

    cost = w_collision * sum_t gamma^t [min_j separation_tj <= margin]
         + w_offroad   * sum_t gamma^t [max footprint SDF_t > -road_margin]
         - mean_t (gamma^t min(min_j separation_tj, clearance_cap))
         - w_speed * mean_t v_t

(separation: the SAT gap of :func:`riskflow_env.geometry.separation`, the signed
distance the env's collision check uses; SDF: the map's signed distance at the 9
footprint points, positive off the road, as for the env's off-road check.) Sampling
fixed action sequences and keeping the best is the simplest member of the family of
sampling-based MPC (e.g. the "predictive sampling" baseline of Howell et al., *Predictive
Sampling: Real-time Behaviour Synthesis with MuJoCo*, 2022).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from riskflow_env import dynamics as unicycle
from riskflow_env.config import DynamicsConfig, is_integer
from riskflow_env.geometry import footprint_points, separation
from riskflow_env.view import SceneView

ACCELS = (-8.0, -5.0, -3.0, -1.5, 0.0, 1.5, 3.0, 5.0)  # [m/s^2]
YAW_RATES = (-0.3, -0.15, -0.07, -0.03, 0.0, 0.03, 0.07, 0.15, 0.3)  # [rad/s]
DURATIONS = (5, 15)  # [steps] of the lane-change shape; the horizon adds constant turns


def candidate_actions(
    horizon: int,
    accels: tuple[float, ...] = ACCELS,
    yaw_rates: tuple[float, ...] = YAW_RATES,
    durations: tuple[int, ...] = DURATIONS,
) -> np.ndarray:
    """(M, horizon, 2) distinct candidate sequences (module docstring), M <= the product
    of the option counts (duplicates, e.g. every shape of a zero yaw rate, are dropped)."""
    shapes = []
    for d in sorted({min(d, horizon) for d in (*durations, horizon)}):
        yaw = np.zeros(horizon)
        yaw[:d] = 1.0
        yaw[d : 2 * d] = -1.0
        shapes.append(yaw)
    yaw = np.asarray(yaw_rates, dtype=np.float64)[:, None, None] * np.stack(shapes)  # (Y, S, H)
    accel = np.asarray(accels, dtype=np.float64)[:, None, None, None]  # (A, 1, 1, 1)
    accel, yaw = np.broadcast_arrays(accel, yaw[None])  # (A, Y, S, H) each
    actions = np.stack((accel, yaw), axis=-1).reshape(-1, horizon, 2)
    return np.unique(actions, axis=0)


class ConstantVelocityPrediction:
    """Every vehicle keeps its current speed and heading (zero actions through the env's
    dynamics): the prediction of :class:`SamplingMPCPlanner`."""

    def __init__(self, dynamics: DynamicsConfig | None = None) -> None:
        self.dynamics = dynamics or DynamicsConfig()

    def predicted_states(self, view: SceneView, steps: int) -> np.ndarray:
        """(A, steps, 4) states (x, y [m], v [m/s], psi [rad]) after each of the next
        ``steps`` steps."""
        still = np.zeros((view.num_agents, steps, 2))
        return unicycle.rollout(view.history[:, -1], still, self.dynamics)


class SamplingMPCPlanner:
    """Sampling MPC with a prediction of the other vehicles; an ``EgoPlanner`` (module
    docstring).

    Args:
        prediction: what the other vehicles will do: any object with
            ``predicted_states(view, steps) -> (A, steps, 4)``; default
            :class:`ConstantVelocityPrediction`.
        horizon: look-ahead [steps].
        dynamics: the env's dynamics (time step and bounds).
        margin: separation [m] below which a predicted step counts as a collision.
        road_margin: SDF [m] above which (i.e. closer to the edge than this) a footprint
            point counts as off the road.
        gamma: per-step discount of the cost terms.
        w_collision, w_offroad, w_speed: cost weights (module docstring).
        clearance_cap: separation [m] beyond which more clearance is worth nothing.
    """

    def __init__(
        self,
        prediction: Any = None,
        horizon: int = 30,
        dynamics: DynamicsConfig | None = None,
        margin: float = 0.3,
        road_margin: float = 0.1,
        gamma: float = 0.95,
        w_collision: float = 10.0,
        w_offroad: float = 10.0,
        w_speed: float = 0.02,
        clearance_cap: float = 5.0,
        candidates: np.ndarray | None = None,
    ) -> None:
        if not (is_integer(horizon) and horizon >= 1):
            raise ValueError(f"horizon must be an int >= 1 [steps], got {horizon!r}")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma!r}")
        self.horizon, self.dynamics = int(horizon), dynamics or DynamicsConfig()
        self.prediction = prediction
        if prediction is None:
            self.prediction = ConstantVelocityPrediction(self.dynamics)
        self.margin, self.road_margin = float(margin), float(road_margin)
        self.weights = (float(w_collision), float(w_offroad), float(w_speed))
        self.clearance_cap = float(clearance_cap)
        self.discount = gamma ** np.arange(horizon)
        self.candidates = candidate_actions(horizon) if candidates is None else candidates
        if self.candidates.ndim != 3 or self.candidates.shape[1:] != (horizon, 2):
            raise ValueError(
                f"candidates must have shape (M, horizon={horizon}, 2), got {self.candidates.shape}"
            )

    def reset(self, view: SceneView) -> None:
        """Nothing to prepare (the candidates are fixed)."""

    def __call__(self, observation: np.ndarray | None, view: SceneView) -> np.ndarray:
        """(2,) (accel [m/s^2], yaw rate [rad/s]): first action of the cheapest candidate."""
        return self.candidates[int(np.argmin(self.costs(view))), 0].copy()

    def costs(self, view: SceneView) -> np.ndarray:
        """(M,) cost of every candidate from the current scene (module docstring)."""
        exact_below = max(self.clearance_cap, self.margin)  # the cost reads no larger gap
        paths, gap, edge = self.outcomes(view, exact_below=exact_below)
        w_collision, w_offroad, w_speed = self.weights
        discount = self.discount
        return (
            w_collision * ((gap <= self.margin) * discount).sum(-1)
            + w_offroad * ((edge > -self.road_margin) * discount).sum(-1)
            - (np.minimum(gap, self.clearance_cap) * discount).sum(-1) / discount.sum()
            - w_speed * paths[..., 2].mean(-1)
        )

    def outcomes(
        self, view: SceneView, exact_below: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What every candidate leads to under the prediction.

        Args:
            view: the current scene.
            exact_below: gaps up to this [m] are exact; a vehicle that is certainly
                farther than this from every candidate at a step (a bound from the
                candidates' spread and the boxes' extents) is skipped at that step, so
                larger gaps may read larger than they are (inf). Callers that clip the
                gap (the cost, the RL features) pass their clip and save most of the
                pairs; the default computes every pair.

        Returns:
            ``paths`` (M, H, 4) the ego's states, ``gap`` (M, H) its separation [m] from
            the nearest predicted vehicle (inf when there is none) and ``edge`` (M, H) the
            largest map SDF over its footprint [m] (positive: partly off the road).
        """
        ego = view.history[0, -1]
        length, width = view.length, view.width
        paths = unicycle.rollout(ego[None], self.candidates, self.dynamics)  # (M, H, 4)
        predicted = self.prediction.predicted_states(view, self.horizon)  # (A, H, 4)
        others = view.present & view.active & ~np.isnan(predicted[:, 0, 0])
        others[0] = False
        gap = np.full(paths.shape[:2], np.inf)
        boxes, lengths, widths = predicted[others], length[others], width[others]  # (B, H, 4)
        step, other = _pairs_within(paths, boxes, length[0], width[0], lengths, widths, exact_below)
        if step.size:  # pairs ordered by step: the min over each step's run of pairs
            pair_gap = separation(
                paths[:, step, :2], paths[:, step, 3], length[0], width[0],
                boxes[other, step, :2], boxes[other, step, 3], lengths[other], widths[other],
            )  # fmt: skip  # (M, P)
            starts = np.flatnonzero(np.diff(step, prepend=-1))
            gap[:, step[starts]] = np.minimum.reduceat(pair_gap, starts, axis=1)
        footprint = footprint_points(paths[..., :2], paths[..., 3], length[0], width[0])
        edge = view.map.sdf_at(footprint).max(axis=-1)  # (M, H)
        return paths, gap, edge


def _pairs_within(
    paths: np.ndarray,
    boxes: np.ndarray,
    length: float,
    width: float,
    lengths: np.ndarray,
    widths: np.ndarray,
    limit: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(step, other) index pairs, step-major, of the predicted boxes (B, H, 4) that may come
    within ``limit`` [m] of separation from some candidate path (M, H, 4) at that step.

    A lower bound on the SAT separation (:func:`~riskflow_env.geometry.separation`) of the
    ego box a and a box b: on the better of a's two axes the centre offset is at least
    ``|c_b - c_a| / sqrt(2)``, a's half extent there at most ``max(length, width) / 2``
    and b's at most its half diagonal. ``|c_b - c_a|`` is at least b's distance from the
    candidates' mean position at that step minus their largest distance from it.
    """
    if not np.isfinite(limit):
        step, other = np.nonzero(np.ones(boxes.shape[1::-1], dtype=bool))
        return step, other
    centre = paths[..., :2].mean(axis=0)  # (H, 2)
    spread = np.linalg.norm(paths[..., :2] - centre, axis=-1).max(axis=0)  # (H,)
    distance = np.linalg.norm(boxes[..., :2] - centre, axis=-1).T - spread[:, None]  # (H, B)
    reach = 0.5 * max(length, width) + 0.5 * np.hypot(lengths, widths)  # (B,)
    near = distance / np.sqrt(2.0) - reach < limit + 1.0  # 1 m of slack for rounding
    return np.nonzero(near)


class OraclePlanner(SamplingMPCPlanner):
    """:class:`SamplingMPCPlanner` that predicts with the adversary's own plans
    (privileged: a reference for what is avoidable, not a planner to deploy).

    Args:
        policy: the scene policy whose plans it reads (a RiskFlow adversary or any
            plan-buffer policy); or give it later with :meth:`watch` (what
            :func:`policies.rl.evaluation.evaluate` does).
        **options: as :class:`SamplingMPCPlanner` (but ``prediction``).
    """

    def __init__(self, policy: Any = None, **options: Any) -> None:
        super().__init__(prediction=None, **options)
        self.prediction = None if policy is None else self.watch(policy)

    def watch(self, policy: Any) -> Any:
        """Read the plans of ``policy`` from now on; returns it.

        Raises:
            TypeError: ``policy`` has no plans to read (e.g. IDM traffic).
        """
        if not callable(getattr(policy, "predicted_states", None)):
            raise TypeError(
                "OraclePlanner needs a scene policy with plans (predicted_states), "
                f"got {type(policy).__name__}"
            )
        self.prediction = policy
        return policy

    def outcomes(
        self, view: SceneView, exact_below: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`SamplingMPCPlanner.outcomes` under the adversary's plans."""
        if self.prediction is None:
            raise RuntimeError("OraclePlanner has no scene policy to read: call watch(policy)")
        return super().outcomes(view, exact_below)
