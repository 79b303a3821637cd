"""The two guidance objectives, shared by RiskFlow and the guided baselines.

* ``L_adv`` (:func:`adversarial_loss`): pulls controllable agents toward their targets.
* ``L_map`` (:func:`map_loss`, :class:`MapTerm`): keeps their footprints on the road.

Definitions, sign and weight conventions: :mod:`policies.riskflow.guidance`. Every
guided method (RiskFlow's output-space guidance, the CTG / CTG++ / CCDiff-style
diffusion guidance, STRIVE-style latent optimisation) uses these same functions, so a
comparison between them is a comparison of how they guide, not of what they optimise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import torch
from torch import Tensor

from riskflow_env._array import attach_gradient, requires_grad
from riskflow_env.geometry import footprint_points
from riskflow_env.maps import DrivableMap

__all__ = [
    "ObjectiveConfig",
    "TARGETS",
    "Target",
    "MapTerm",
    "adversarial_loss",
    "adversarial_value_and_gradient",
    "map_loss",
    "map_term",
    "target_rows",
]


class Target(str, Enum):
    """Whom the adversarial term pulls the controllable vehicles toward."""

    OTHERS = "others"
    """every present vehicle outside ``A_c``, the ego included (the RiskFlow paper's)"""
    EGO = "ego"
    """the ego only (stress-testing an ego planner)"""


TARGETS = tuple(target.value for target in Target)  # ("others", "ego")


@dataclass(frozen=True)
class ObjectiveConfig:
    """The guidance objective every guided adversary shares (RiskFlow, STRIVE-style, the
    diffusion baselines): ``lambda_adv * L_adv + lambda_map * L_map``.

    Attributes:
        lambda_adv: weight of ``L_adv`` [1/m]; > 0 is adversarial (RiskFlow's convention).
        lambda_map: weight of ``L_map`` [1/m^2], >= 0.
        horizon: ``T_g`` plan steps of ``L_adv``; None: the whole plan.
        target: a :class:`Target` value, ``"others"`` (paper) or ``"ego"`` (stress testing).
        map_margin: footprint samples closer than this to the road edge are penalised [m].
        map_decay: ``w_t = map_decay ** t`` of ``L_map``, in (0, 1].
    """

    lambda_adv: float = 50.0
    lambda_map: float = 1.0
    horizon: int | None = None
    target: str = "others"
    map_margin: float = 0.2
    map_decay: float = 0.98

    def checks(self) -> list[tuple[bool, str]]:
        """``(holds, message)`` of every option rule (subclasses add theirs)."""
        horizon_ok = (
            self.horizon is None
            or (isinstance(self.horizon, int) and not isinstance(self.horizon, bool))
            and self.horizon >= 1
        )
        reals = ("lambda_adv", "lambda_map", "map_margin", "map_decay")
        return [
            (horizon_ok, "horizon must be None or an int >= 1"),
            (all(math.isfinite(getattr(self, name)) for name in reals), f"{reals} must be finite"),
            (self.lambda_map >= 0, "lambda_map must be >= 0"),
            (0 < self.map_decay <= 1, "map_decay must be in (0, 1]"),
            (self.target in TARGETS, f"target must be one of {TARGETS}"),
        ]

    def __post_init__(self) -> None:
        for ok, message in self.checks():
            if not ok:
                raise ValueError(f"{type(self).__name__}: {message}; got {self}")


def target_rows(present: Tensor, controllable: Tensor, ego: int, target: str) -> Tensor:
    """(A,) bool: the agents ``L_adv`` pulls the controllable ones toward.

    Args:
        present: (A,) bool agents in the scene.
        controllable: (A,) bool ``A_c``.
        ego: slot of the ego.
        target: ``"others"`` (the paper's: every present agent outside ``A_c``, the ego
            included) or ``"ego"`` (the ego only, for stress-testing an ego planner).
    """
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}; got {target!r}")
    if target == Target.EGO:
        targets = torch.zeros_like(present, dtype=torch.bool)
        targets[ego] = True
        return targets
    return present.bool() & ~controllable.bool()


def map_term(scene, rows: Tensor, steps: int, config) -> MapTerm | None:
    """The :class:`MapTerm` of the controllable ``rows`` of ``scene`` (anything with
    ``drivable_map``, ``frame``, ``length`` and ``width``: a planning scene), or None when
    ``L_map`` is off (no map, or ``config.lambda_map == 0``); ``config`` has
    ``lambda_map``, ``map_margin`` and ``map_decay`` (every guided method's config does)."""
    if scene.drivable_map is None or config.lambda_map == 0:
        return None
    length, width = scene.length[rows], scene.width[rows]
    return MapTerm(
        scene.drivable_map, scene.frame, length, width, steps, config.map_margin, config.map_decay
    )


def adversarial_loss(xy: Tensor, target_xy: Tensor, horizon: int | None = None) -> Tensor:
    """``L_adv``: summed over agents, mean over ``t < horizon`` of the nearest-target distance.

    Differentiable with respect to ``xy`` (targets are constants): the value and its
    gradient come from :func:`adversarial_value_and_gradient`.

    Args:
        xy: (C, T, 2) [m] controllable agents' positions.
        target_xy: (J, T, 2) [m] targets' positions.
        horizon: ``T_g`` steps; None: all.

    Returns:
        scalar [m]; 0 if there is no agent or no target.
    """
    if not requires_grad(xy):
        return _adversarial(xy, target_xy, horizon, with_gradient=False)[0]
    value, gradient = _adversarial(xy.detach(), target_xy, horizon, with_gradient=True)
    return attach_gradient(value, xy, gradient, axis=None)


def adversarial_value_and_gradient(
    xy: Tensor, target_xy: Tensor, horizon: int | None = None
) -> tuple[Tensor, Tensor]:
    """:func:`adversarial_loss` [m] and its gradient (C, T, 2) [m/m] with respect to ``xy``.

    The gradient of a min is the gradient at the argmin; ``(1 / T_g)`` times the unit
    vector from the nearest target to the agent for ``t < T_g`` (0 where the agent sits
    exactly on it), 0 beyond ``T_g``. No autograd graph is built.
    """
    return _adversarial(xy.detach(), target_xy.detach(), horizon, with_gradient=True)


def _adversarial(
    xy: Tensor, target_xy: Tensor, horizon: int | None, with_gradient: bool
) -> tuple[Tensor, Tensor | None]:
    """The one implementation of :func:`adversarial_loss` (and its gradient)."""
    near, target_xy = xy[:, :horizon], target_xy[:, :horizon].detach()
    if near.shape[0] == 0 or target_xy.shape[0] == 0:
        return near.sum() * 0.0, torch.zeros_like(xy) if with_gradient else None
    with torch.no_grad():
        offsets = near[:, None] - target_xy[None]  # (C, J, T_g, 2)
        nearest = (offsets * offsets).sum(dim=-1).argmin(dim=1)  # (C, T_g)
    steps = torch.arange(near.shape[1], device=xy.device)
    offset = near - target_xy[nearest, steps]  # (C, T_g, 2)
    distance = torch.linalg.vector_norm(offset, dim=-1)  # (C, T_g)
    value = distance.sum() / near.shape[1]
    if not with_gradient:
        return value, None
    scale = torch.where(distance > 0, distance * near.shape[1], torch.inf)  # 0 on a target
    gradient = torch.zeros_like(xy)
    gradient[:, : near.shape[1]] = offset / scale[..., None]
    return value, gradient


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
    """``L_map`` with its constants (rotation to the world frame, ``w_t``) made once."""

    def __init__(
        self,
        drivable_map: DrivableMap,
        frame: Tensor,
        length: Tensor,
        width: Tensor,
        steps: int,
        margin: float,
        decay: float,
    ) -> None:
        cos, sin = torch.cos(frame[2]), torch.sin(frame[2])
        self.rotation_t = torch.stack([torch.stack([cos, sin]), torch.stack([-sin, cos])])
        self.origin, self.yaw = frame[:2], frame[2]
        # The footprint samples in each vehicle's own frame, (C, 1, 9) along and across [m]
        # (``footprint_points`` at the origin with heading 0: the one definition of them).
        zero = torch.zeros_like(length)
        local = footprint_points(torch.stack([zero, zero], dim=-1), zero, length, width)
        self.along, self.across = local[:, None, :, 0], local[:, None, :, 1]
        self.map, self.margin = drivable_map, margin
        self.weights = decay ** torch.arange(steps, device=frame.device, dtype=frame.dtype)

    def __call__(self, trajectories: Tensor) -> Tensor:
        """Scalar ``L_map`` [m^2] of (C, T, 4) scene-frame states, differentiable with
        respect to them (value and gradient from :meth:`value_and_gradient`)."""
        if not requires_grad(trajectories):
            return self._evaluate(trajectories, with_gradient=False)[0]
        value, gradient = self._evaluate(trajectories.detach(), with_gradient=True)
        return attach_gradient(value, trajectories, gradient, axis=None)

    def value_and_gradient(self, trajectories: Tensor) -> tuple[Tensor, Tensor]:
        """``L_map`` [m^2] and its gradient (C, T, 4) with respect to the states
        (x, y [m^2/m], v: 0, psi [m^2/rad]); no autograd graph is built."""
        return self._evaluate(trajectories.detach(), with_gradient=True)

    def _evaluate(self, trajectories: Tensor, with_gradient: bool) -> tuple[Tensor, Tensor | None]:
        """The one implementation of the value and its (chain-rule) gradient."""
        world = trajectories[..., :2] @ self.rotation_t + self.origin  # (C, T, 2)
        yaw = (trajectories[..., 3] + self.yaw)[..., None]
        cos, sin = torch.cos(yaw), torch.sin(yaw)  # (C, T, 1)
        along_x, across_x = cos * self.along, sin * self.across  # (C, T, 9)
        along_y, across_y = sin * self.along, cos * self.across
        x = world[..., :1] + along_x - across_x  # (C, T, 9)
        y = world[..., 1:] + along_y + across_y
        points = torch.stack([x, y], dim=-1)  # == footprint_points(world, yaw, ...)
        if not with_gradient:
            depth = torch.relu(self.map.sdf_at(points) + self.margin)  # (C, T, 9)
            return ((depth * depth).sum(dim=-1) * self.weights).sum(), None
        sdf, sdf_gradient = self.map.sdf_with_gradient(points)  # (C, T, 9), (C, T, 9, 2)
        depth = torch.relu(sdf + self.margin)
        value = ((depth * depth).sum(dim=-1) * self.weights).sum()
        # dL/dq for each sample q = world + R(yaw) * local, then the chain rule to the state:
        # world = xy @ rotation_t + origin, dq/dyaw = (-(q_y - world_y), q_x - world_x).
        slope = (2.0 * depth * self.weights[:, None])[..., None] * sdf_gradient  # (C, T, 9, 2)
        d_xy = slope.sum(dim=-2) @ self.rotation_t.T  # (C, T, 2)
        d_yaw = (slope[..., 1] * (along_x - across_x) - slope[..., 0] * (along_y + across_y)).sum(
            dim=-1
        )
        d_speed = torch.zeros_like(d_yaw)
        return value, torch.cat([d_xy, d_speed[..., None], d_yaw[..., None]], dim=-1)
