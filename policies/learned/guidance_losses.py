"""The guidance objective's terms, shared by RiskFlow and the guided baselines.

* ``L_adv`` (:func:`adversarial_loss`): pulls controllable agents toward their targets.
* ``L_map`` (:func:`map_loss`, :class:`MapTerm`): keeps their footprints on the road.
* ``L_sep`` (:mod:`policies.learned.plan_overlap`): keeps the guided vehicles of a
  scene apart from each other (not in the RiskFlow paper's objective; ``lambda_sep = 0``
  drops it).

Definitions, sign and weight conventions: :mod:`policies.riskflow.guidance`. Every
guided method (RiskFlow's output-space guidance, the CTG / CTG++ / CCDiff-style
diffusion guidance, STRIVE-style latent optimisation) uses these same functions, so a
comparison between them is a comparison of how they guide, not of what they optimise.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
import torch
from torch import Tensor

from policies.learned.adversarial_term import (
    adversarial_loss,
    adversarial_rows,
    adversarial_value_and_gradient,
)
from policies.learned.ranking import MIN_ATTACK_SPEED
from riskflow_env._array import attach_gradient, requires_grad
from riskflow_env.config import check_field_types, is_integer
from riskflow_env.geometry import footprint_points
from riskflow_env.maps import DrivableMap, MapStack

__all__ = [
    "HUMAN_ACCEL",
    "HUMAN_YAW_RATE",
    "KEEP_MOVING",
    "LAMBDA_KEEP_MOVING",
    "HORIZONS",
    "ObjectiveConfig",
    "TARGETS",
    "Target",
    "MapTerm",
    "adversarial_loss",
    "adversarial_rows",
    "adversarial_value_and_gradient",
    "bystander_rows",
    "map_loss",
    "map_term",
    "sum_per_scene",
    "target_rows",
]


class Target(str, Enum):
    """Whom the adversarial term pulls the controllable vehicles toward."""

    OTHERS = "others"
    """every present vehicle outside ``A_c``, the ego included (the RiskFlow paper's)"""
    EGO = "ego"
    """the ego only, by one attacker at most (stress-testing an ego planner; the attacker:
    :func:`policies.learned.ranking.ego_attacker`)"""


TARGETS = tuple(target.value for target in Target)  # ("others", "ego")
HUMAN_ACCEL = 6.0
"""[m/s^2] the p99 |acceleration| of the data the shipped generator learned from
(``policies.stress.failures.HUMAN_BOUNDS``, the bound the failure analysis holds attackers
to); the dynamics allow braking at 8 m/s^2. With target ``"ego"``, output-space guidance
keeps the attacker's acceleration and braking within it (brake-checks in front of the
ego at 6.2-6.8 m/s^2 made attackers implausible); the avoidance steps' braking fallback
brakes at most this hard (:func:`policies.learned.plan_avoidance.brake_to_clear`)."""
HUMAN_YAW_RATE = 0.9241
"""[rad/s] the p99 |yaw rate| of the same data (``HUMAN_BOUNDS``); the dynamics allow
1 rad/s. With target ``"ego"``, guidance keeps the attacker's yaw rate within it as it
keeps its acceleration within ``HUMAN_ACCEL`` (attackers that cut across a roundabout at
0.96-0.99 rad/s were implausible)."""
KEEP_MOVING = MIN_ATTACK_SPEED
"""[m/s] with target ``"ego"``, the attacker keeps moving: over the guidance horizon its
guided plan's speed stays at ``min(its speed now, KEEP_MOVING)`` or above, by the penalty
``LAMBDA_KEEP_MOVING * sum_t relu(floor - v_t)^2`` (:func:`keep_moving_gradient`). An
attacker free to brake to a standstill in front of the ego brake-checked it to a stop and
then stood in the lane for the rest of the episode, where the ego, stopped behind it, could
be attacked no more (13 of the IDM ego's 21 standing episodes in 40 scenes ended behind the
former attacker at 0 m/s). The floor is the slowest ego that may be attacked
(``policies.learned.ranking.MIN_ATTACK_SPEED``, 2 m/s): an attacker may brake as hard as a
human (``HUMAN_ACCEL``) down to the slowest it could still attack, not stop in the lane.
What it changes: docs/explanation/results.md, section 6."""
LAMBDA_KEEP_MOVING = 10.0
"""[1/(m/s)^2] the weight of the attacker's speed floor (:data:`KEEP_MOVING`)."""
HORIZONS = {"others": None, "ego": 30}
"""[steps] the default ``T_g`` of ``L_adv``, ``L_map`` and ``L_sep`` per target: the whole plan
with ``"others"`` (the paper's), 3 s with ``"ego"``. Attacking the ego over the whole 5 s plan,
the mean distance pulls the plan's tail toward where the ego will be long after the
attacker could reach it: the steps bend the heading of the whole plan, the tail leaves
the road, and the map term's gradient then outweighs the attack for the rest of the
steps (Adam's momentum carries it). Over 3 s the IDM ego is hit in 23% of 300 episodes
against 17% over the whole plan (docs/explanation/results.md, section 6)."""


@dataclass(frozen=True)
class ObjectiveConfig:
    """The guidance objective every guided adversary shares (RiskFlow, STRIVE-style, the
    diffusion baselines): ``lambda_adv * L_adv + lambda_map * L_map``.

    Attributes:
        lambda_adv: weight of ``L_adv`` [1/m]; > 0 is adversarial (RiskFlow's convention).
        lambda_map: weight of ``L_map`` [1/m^2], >= 0. The default 20 keeps the guided
            vehicles' footprints on the road (<= 2% of their steps off it, attacking the
            ego, where 1 left 6%; docs/explanation/method.md).
        horizon: ``T_g`` plan steps of ``L_adv``, ``L_map`` and ``L_sep``; None: the
            target's default (``HORIZONS``: the whole plan with ``"others"``, 3 s with
            ``"ego"``).
        target: a :class:`Target` value, ``"others"`` (paper) or ``"ego"`` (stress testing).
        map_margin: footprint samples closer than this to the road edge are penalised [m].
        map_decay: ``w_t = map_decay ** t`` of ``L_map``, in (0, 1].
        lambda_sep: weight [1/m^2] of ``L_sep``, the summed squared penetration depth of
            the pairs of guided boxes of a scene over the guidance horizon, >= 0: it keeps
            the guided vehicles from converging on each other (default 100; 0: off, the
            paper's objective).
    """

    lambda_adv: float = 50.0
    lambda_map: float = 20.0
    horizon: int | None = None
    target: str = "others"
    map_margin: float = 0.2
    map_decay: float = 0.98
    lambda_sep: float = 100.0

    @property
    def resolved_horizon(self) -> int | None:
        """``T_g`` in use: ``horizon``, or the target's default when it is None (so a copy
        with another ``target``, e.g. a curriculum's, takes that target's); None: the
        whole plan."""
        return HORIZONS[self.target] if self.horizon is None else self.horizon

    def checks(self) -> list[tuple[bool, str]]:
        """``(holds, message)`` of every option rule (subclasses add theirs)."""
        horizon_ok = self.horizon is None or (is_integer(self.horizon) and self.horizon >= 1)
        reals = ("lambda_adv", "lambda_map", "map_margin", "map_decay")
        return [
            (horizon_ok, "horizon must be None or an int >= 1"),
            (all(math.isfinite(getattr(self, name)) for name in reals), f"{reals} must be finite"),
            (self.lambda_map >= 0, "lambda_map must be >= 0"),
            (
                math.isfinite(self.lambda_sep) and self.lambda_sep >= 0,
                "lambda_sep must be a finite number >= 0",
            ),
            (0 < self.map_decay <= 1, "map_decay must be in (0, 1]"),
            (self.target in TARGETS, f"target must be one of {TARGETS}"),
        ]

    def __post_init__(self) -> None:
        check_field_types(self, lambda name: f"{type(self).__name__}: {name}")
        for ok, message in self.checks():
            if not ok:  # the value of the field the rule names, or every field
                name = message.split()[0]
                got = f"{name}={getattr(self, name)!r}" if hasattr(self, name) else str(self)
                raise ValueError(f"{type(self).__name__}: {message}; got {got}")
        for field in dataclasses.fields(self):  # numpy integers as Python ints
            value = getattr(self, field.name)
            if isinstance(value, np.integer):
                object.__setattr__(self, field.name, int(value))


def target_rows(present: Tensor, controllable: Tensor, ego: int, target: str) -> Tensor:
    """(A,) bool: the agents ``L_adv`` pulls the controllable ones toward.

    Args:
        present: (A,) bool agents in the scene, or (B, A) for B scenes.
        controllable: ``A_c``, the shape of ``present``.
        ego: slot of the ego (in every scene).
        target: ``"others"`` (the paper's: every present agent outside ``A_c``, the ego
            included) or ``"ego"`` (the ego only, for stress-testing an ego planner).
    """
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}; got {target!r}")
    if target == Target.EGO:
        targets = torch.zeros_like(present, dtype=torch.bool)
        targets[..., ego] = True
        return targets
    return present.bool() & ~controllable.bool()


def bystander_rows(present: Tensor, guided: Tensor, targets: Tensor) -> tuple[Tensor, Tensor]:
    """The bystanders of B scenes, the present agents neither guided nor a target (with
    target ``"ego"``, the vehicles that keep their unguided plans; none with ``"others"``):
    their flat indices into the ``B * A`` agents and the scene of each, (O,) both, from
    (B, A) bool ``present``, ``guided`` and ``targets``."""
    flat = torch.nonzero((present & ~guided & ~targets).reshape(-1)).flatten()
    return flat, torch.div(flat, present.shape[-1], rounding_mode="floor")


def keep_moving_gradient(speed: Tensor, floor: Tensor, horizon: int | None) -> Tensor:
    """``d/dv`` (C, T) of ``LAMBDA_KEEP_MOVING * sum_{t < horizon} relu(floor - v_t)^2``,
    the attacker's speed floor (:data:`KEEP_MOVING`), from (C, T) planned speeds [m/s] and
    (C,) floors [m/s]; 0 beyond ``horizon`` (None: the whole plan)."""
    short = torch.relu(floor[:, None] - speed)
    if horizon is not None:
        short[:, horizon:] = 0.0
    return (-2.0 * LAMBDA_KEEP_MOVING) * short


def sum_per_scene(values: Tensor, scene_of_row: Tensor, num_scenes: int) -> Tensor:
    """(C, ...) values of rows of B scenes (``scene_of_row`` (C,)) summed per scene:
    (B, ...) (the per-scene losses of batched guidance)."""
    total = values.new_zeros(num_scenes, *values.shape[1:])
    return total.index_add_(0, scene_of_row, values)


def map_term(
    scene, rows: Tensor, steps: int, config, scene_of_row: Tensor | None = None, scored=None
):
    """The :class:`MapTerm` of the controllable ``rows`` of ``scene`` (anything with
    ``drivable_map``, ``frame``, ``length`` and ``width``: a planning scene), or None when
    ``L_map`` is off (no map, or ``config.lambda_map == 0``); ``config`` has
    ``lambda_map``, ``map_margin``, ``map_decay`` and ``resolved_horizon`` (every guided
    method's config does). It scores the first ``scored`` of the ``steps`` plan steps;
    None: the objective's ``T_g``, the horizon of the other terms (the plan's later steps
    are never executed: the plans are made again every cycle, and scoring them pulled an
    attack back where a plan heading for the ego would leave the road seconds after the
    horizon).

    Rows of several scenes (batched planning): ``scene.frame`` is (B, 3), the map a
    :class:`~riskflow_env.maps.MapStack` of the B scenes' maps (or one map they share), and
    ``scene_of_row`` (C,) the scene of each row; ``rows`` index the flattened agents.
    """
    if scene.drivable_map is None or config.lambda_map == 0:
        return None
    length, width = scene.length[rows], scene.width[rows]
    drivable_map, frame = scene.drivable_map, scene.frame
    if scene_of_row is not None:
        if isinstance(drivable_map, MapStack):
            drivable_map = drivable_map.select(scene_of_row)
        frame = frame[scene_of_row] if frame.ndim == 2 else frame
    return MapTerm(
        drivable_map, frame, length, width, steps, config.map_margin, config.map_decay,
        horizon=config.resolved_horizon if scored is None else scored,
    )  # fmt: skip


def map_loss(
    trajectories: Tensor,
    length: Tensor,
    width: Tensor,
    drivable_map: DrivableMap,
    frame: Tensor,
    margin: float = 0.2,
    decay: float = 0.98,
) -> Tensor:
    """``L_map``: decayed squared off-road depth of the footprint samples.

    Args:
        trajectories: (C, T, 4) states in the scene frame.
        length: (C,) [m].
        width: (C,) [m].
        drivable_map: the map, world frame.
        frame: (3,) world pose (x [m], y [m], psi [rad]) of the scene frame.
        margin: [m] added to the SDF before the penalty.
        decay: ``w_t = decay ** t``.

    Returns:
        scalar [m^2].
    """
    return MapTerm(drivable_map, frame, length, width, trajectories.shape[1], margin, decay)(
        trajectories
    )


class MapTerm:
    """``L_map`` with its constants (rotation to the world frame, ``w_t``) made once.

    Args:
        drivable_map: the map (world frame), or any object with its ``sdf_at`` and
            ``sdf_with_gradient`` taking (C, ...) queries (``MapStack.select``: a map per row).
        frame: (3,) world pose (x [m], y [m], psi [rad]) of the scene frame, or (C, 3)
            one per row (rows of several scenes).
        length: (C,) [m].
        width: (C,) [m].
        steps: plan steps T.
        margin: [m] added to the SDF before the penalty.
        decay: ``w_t = decay ** t``.
        horizon: only the first ``horizon`` steps are scored (``w_t = 0`` after); None:
            every step.
    """

    def __init__(
        self,
        drivable_map: DrivableMap | MapStack.Selection,
        frame: Tensor,
        length: Tensor,
        width: Tensor,
        steps: int,
        margin: float,
        decay: float,
        horizon: int | None = None,
    ) -> None:
        frame = frame[None] if frame.ndim == 1 else frame  # (1 or C, 3)
        self.cos, self.sin = torch.cos(frame[:, 2:]), torch.sin(frame[:, 2:])  # (1 or C, 1)
        self.origin_x, self.origin_y, self.yaw = frame[:, :1], frame[:, 1:2], frame[:, 2:]
        # The footprint samples in each vehicle's own frame, (C, 1, 9) along and across [m]
        # (``footprint_points`` at the origin with heading 0: the one definition of them).
        zero = torch.zeros_like(length)
        local = footprint_points(torch.stack([zero, zero], dim=-1), zero, length, width)
        self.along, self.across = local[:, None, :, 0], local[:, None, :, 1]
        self.map, self.margin = drivable_map, margin
        t = torch.arange(steps, device=frame.device, dtype=frame.dtype)
        self.weights = decay**t
        if horizon is not None:
            self.weights[horizon:] = 0.0

    def __call__(self, trajectories: Tensor) -> Tensor:
        """Scalar ``L_map`` [m^2] of (C, T, 4) scene-frame states, differentiable with
        respect to them (value and gradient from :meth:`value_and_gradient`)."""
        if not requires_grad(trajectories):
            return self._evaluate(trajectories, with_gradient=False)[0].sum()
        value, gradient = self.value_and_gradient(trajectories)
        return attach_gradient(value, trajectories, gradient, axis=None)

    def value_and_gradient(self, trajectories: Tensor) -> tuple[Tensor, Tensor]:
        """``L_map`` [m^2] and its gradient (C, T, 4) with respect to the states
        (x, y [m^2/m], v: 0, psi [m^2/rad]); no autograd graph is built."""
        values, gradient = self.rows_and_gradient(trajectories)
        return values.sum(), gradient

    def rows_and_gradient(self, trajectories: Tensor) -> tuple[Tensor, Tensor]:
        """(C,) ``L_map`` [m^2] of each row and the gradient, as :meth:`value_and_gradient`."""
        return self._evaluate(trajectories.detach(), with_gradient=True)

    def rows(self, trajectories: Tensor) -> Tensor:
        """(C,) ``L_map`` [m^2] of each row (no gradient)."""
        return self._evaluate(trajectories.detach(), with_gradient=False)[0]

    def forgive(self, current: Tensor) -> None:
        """Forgive each row what its footprint is off the road now: the penalty starts
        beyond the current depth ``max(0, sdf + margin)`` of its footprint samples at
        ``current`` (C, 4) scene-frame states, as the training penalty forgives what the
        log does (:func:`policies.learned.plan_penalties.offroad_penalty`). A vehicle on
        the road now keeps the plain term; one that the map shows off the road (a car park
        the raster misses) is not pulled onto it."""
        points = self._footprint(current[:, None])[0]  # (C, 1, 9, 2)
        depth = torch.relu(self.map.sdf_at(points) + self.margin).amax(dim=(-2, -1))  # (C,)
        self.margin = self.margin - depth[:, None, None]

    def _footprint(self, trajectories: Tensor) -> tuple[Tensor, ...]:
        """World footprint samples (C, T, 9, 2) of scene-frame states and the pieces of
        their rotation (``along_x, across_x, along_y, across_y``, each (C, T, 9))."""
        cos_f, sin_f = self.cos, self.sin  # the scene frame's rotation to the world
        x_s, y_s = trajectories[..., 0], trajectories[..., 1]  # (C, T)
        world_x = self.origin_x + cos_f * x_s - sin_f * y_s
        world_y = self.origin_y + sin_f * x_s + cos_f * y_s
        yaw = (trajectories[..., 3] + self.yaw)[..., None]
        cos, sin = torch.cos(yaw), torch.sin(yaw)  # (C, T, 1)
        along_x, across_x = cos * self.along, sin * self.across  # (C, T, 9)
        along_y, across_y = sin * self.along, cos * self.across
        x = world_x[..., None] + along_x - across_x  # (C, T, 9)
        y = world_y[..., None] + along_y + across_y
        points = torch.stack([x, y], dim=-1)  # == footprint_points(world, yaw, ...)
        return points, along_x, across_x, along_y, across_y

    def _evaluate(self, trajectories: Tensor, with_gradient: bool) -> tuple[Tensor, Tensor | None]:
        """The one implementation of the per-row values and their (chain-rule) gradient."""
        cos_f, sin_f = self.cos, self.sin
        points, along_x, across_x, along_y, across_y = self._footprint(trajectories)
        if not with_gradient:
            depth = torch.relu(self.map.sdf_at(points) + self.margin)  # (C, T, 9)
            return ((depth * depth).sum(dim=-1) * self.weights).sum(dim=-1), None
        sdf, sdf_gradient = self.map.sdf_with_gradient(points)  # (C, T, 9), (C, T, 9, 2)
        depth = torch.relu(sdf + self.margin)
        values = ((depth * depth).sum(dim=-1) * self.weights).sum(dim=-1)
        # dL/dq for each sample q = world + R(yaw) * local, then the chain rule to the state:
        # world = R(frame) xy + origin, dq/dyaw = (-(q_y - world_y), q_x - world_x).
        slope = (2.0 * depth * self.weights[:, None])[..., None] * sdf_gradient  # (C, T, 9, 2)
        d_world = slope.sum(dim=-2)  # (C, T, 2)
        d_x = cos_f * d_world[..., 0] + sin_f * d_world[..., 1]
        d_y = -sin_f * d_world[..., 0] + cos_f * d_world[..., 1]
        d_yaw = (slope[..., 1] * (along_x - across_x) - slope[..., 0] * (along_y + across_y)).sum(
            dim=-1
        )
        gradient = torch.stack([d_x, d_y, torch.zeros_like(d_yaw), d_yaw], dim=-1)
        return values, gradient
