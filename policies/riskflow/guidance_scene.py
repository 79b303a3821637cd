"""What guidance takes and returns for one scene or a batch of B scenes: the scene's base
plans and geometry (:class:`GuidanceScene`), the guided plans (:class:`GuidanceResult`)
and the ``A_c`` rows of B scenes as the batched loops of RiskFlow
(:mod:`policies.riskflow.guidance`) and STRIVE-style (:mod:`policies.baselines.strive`)
take them (:class:`GuidedRows`, :func:`guided_rows`, :func:`flatten_scenes`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from policies.learned.guidance_losses import bystander_rows, sum_per_scene, target_rows
from riskflow_env.maps import DrivableMap


@dataclass(frozen=True)
class GuidanceScene:
    """One scene's plans and what guidance needs about it (torch, scene frame), or B
    scenes' (batched planning: a leading B axis on every tensor, agents padded to A).

    Attributes:
        eps: (A, T, 2) noise, normalised; (B, A, T, 2) for B scenes.
        u0: (A, T, 2) base residual ``u_theta(eps, 0, 1; C)``.
        state: (A, 4) current states (x, y [m], v [m/s], psi [rad]).
        length: (A,) [m].
        width: (A,) [m].
        agent_mask: (A,) bool agents present (False on padding).
        base_actions: (A, T, 2) :func:`plans_from_velocity` of ``u0``.
        base_trajectories: (A, T, 4) their rollout.
        drivable_map: the scene's map (world frame); for B scenes a
            :class:`~riskflow_env.maps.MapStack` of their maps in scene order, or one map
            they all share; None drops ``L_map``.
        frame: (3,) world pose (x [m], y [m], psi [rad]) of the scene frame; (B, 3).
        ego: slot of the ego (in every scene).
    """

    eps: Tensor
    u0: Tensor
    state: Tensor
    length: Tensor
    width: Tensor
    agent_mask: Tensor
    base_actions: Tensor
    base_trajectories: Tensor
    drivable_map: DrivableMap | None
    frame: Tensor
    ego: int = 0


@dataclass(frozen=True)
class GuidanceResult:
    """Guided plans: ``u``, ``actions`` (A, T, 2), ``trajectories`` (A, T, 4) (base plans
    outside ``A_c``) and ``losses`` (steps + 1, 2): ``(L_adv [m], L_map [m^2])`` before
    each step and after the last. For B scenes: (B, A, ...) and losses (steps + 1, B, 2),
    each scene's own."""

    u: Tensor
    actions: Tensor
    trajectories: Tensor
    losses: Tensor


PER_AGENT = (  # the per-agent fields of a GuidanceScene (a leading B axis when batched)
    "eps", "u0", "state", "length", "width", "agent_mask", "base_actions", "base_trajectories",
)  # fmt: skip


@dataclass(frozen=True)
class GuidedRows:
    """The ``A_c`` rows of B scenes, as the batched guidance loops (RiskFlow's,
    STRIVE-style's) take them: ``rows`` (C,) index the flattened ``B * A`` agents,
    ``scene_of_row`` (C,) their scenes, ``target_xy`` (C, A, T, 2) the base plans of each
    row's scene (detached) and ``target_valid`` (C, A) which of them are the row's targets;
    ``bystanders`` (O,) index the flattened agents that are present but neither the ego nor
    guided nor a target (target ``"ego"``: the vehicles that keep their unguided plans;
    none with ``"others"``), ``scene_of_bystander`` (O,) their scenes."""

    rows: Tensor
    scene_of_row: Tensor
    target_xy: Tensor
    target_valid: Tensor
    bystanders: Tensor
    scene_of_bystander: Tensor

    def per_scene(self, values: Tensor, num_scenes: int) -> Tensor:
        """(C, K) values of the rows summed per scene: (B, K)."""
        return sum_per_scene(values, self.scene_of_row, num_scenes)


def guided_rows(scene: GuidanceScene, controllable: Tensor, target: str) -> GuidedRows:
    """The :class:`GuidedRows` of B scenes: ``controllable`` (B, A) among the present
    agents, the ego never; targets by :func:`target_rows` (``"others"`` or ``"ego"``);
    the bystanders, the present agents left (none with ``"others"``)."""
    present = scene.agent_mask.bool()
    mask = controllable.bool() & present
    mask[:, scene.ego] = False
    targets = target_rows(present, mask, scene.ego, target)  # (B, A)
    rows = torch.nonzero(mask.reshape(-1)).flatten()  # flat (scene, agent) indices
    scene_of_row = torch.div(rows, mask.shape[1], rounding_mode="floor")
    target_xy = scene.base_trajectories[..., :2].detach()[scene_of_row]
    bystanders, scene_of_bystander = bystander_rows(present, mask, targets)
    return GuidedRows(
        rows, scene_of_row, target_xy, targets[scene_of_row], bystanders, scene_of_bystander
    )


def flatten_scenes(scene: GuidanceScene) -> GuidanceScene:
    """B scenes' per-agent tensors flattened to ``B * A`` rows (scene after scene); the
    map and the frames (B, 3) stay per scene (rows find theirs by ``scene_of_row``)."""
    return dataclasses.replace(
        scene, **{name: getattr(scene, name).flatten(0, 1) for name in PER_AGENT}
    )


__all__ = [
    "PER_AGENT",
    "GuidanceResult",
    "GuidanceScene",
    "GuidedRows",
    "flatten_scenes",
    "guided_rows",
]
