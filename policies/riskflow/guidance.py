"""Output-space guidance: bend the controllable agents' plans toward risky interactions.

RiskFlow (Lan et al. 2026) guides the *output* of the one-step generator, not its
sampling path: starting from the base residual ``u0 = u_theta(eps, 0, 1; C)``
(normalised action space) it takes ``K_g`` steps

    u <- u - gamma * M_Ac * grad_u L,      L = lambda_adv * L_adv + lambda_map * L_map,

with ``a = denorm(eps + u)`` and the trajectory ``rollout(a, s0)`` (the differentiable
unicycle of ``riskflow_env.dynamics``). The generator is *not* re-run inside the loop:
each step is one rollout of the ``A_c`` rows, their SDF lookups and a backward pass
through those only, in closed form (``L_adv`` and ``L_map`` give their gradient with
respect to the trajectories, :mod:`policies.learned.guidance_losses`; the rollout's
vector-Jacobian product, ``riskflow_env.dynamics.rollout_with_vjp``; ``denorm`` is a
diagonal scale); the gradients agree with autograd to float rounding. Only ``A_c`` rows
are variables: every other row is the base plan, bit for bit. Steps are projected so that
the actions stay inside the dynamics bounds; Adam by default, or the paper's plain steps.

``L_adv`` is the mean distance over the guidance horizon to the nearest target (every
present agent outside ``A_c``, or the ego only), ``L_map`` the decayed squared depth of
the footprint samples off the drivable area over the same horizon; ``lambda_adv > 0`` is
more adversarial (the paper's "-50" is ``+50`` here). A third term, ``lambda_sep *
L_sep`` (weight 100 by default), keeps the guided vehicles of a scene apart from each
other, so that they do not converge on one target as a swarm, and with target ``"ego"``
keeps the attacker clear of the vehicles that keep their unguided plans (held fixed), so
that it does not strike a third vehicle on its way to the ego: ``L_sep`` is the summed
squared penetration depth of those pairs of boxes over the guidance horizon (the
avoidance steps' objective, :func:`~policies.learned.plan_overlap.overlap_gradient`).
The paper's objective has no such term (``lambda_sep=0``). With target ``"ego"`` the
attacker keeps moving (its planned speed is held at ``min(its speed now, 2 m/s)`` or above,
:data:`~policies.learned.guidance_losses.KEEP_MOVING`), its acceleration and yaw rate within
the human bounds (``HUMAN_ACCEL``, ``HUMAN_YAW_RATE``). docs/explanation/method.md
("Output-space guidance") has the terms, the sign convention and why the steps are Adam steps.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from policies.learned import compiled_plans
from policies.learned.adam import Adam
from policies.learned.data import Normalizer
from policies.learned.guidance_losses import (
    HUMAN_ACCEL,
    HUMAN_YAW_RATE,
    KEEP_MOVING,
    TARGETS,
    Target,
    adversarial_loss,
    adversarial_rows,
    adversarial_value_and_gradient,
    bystander_rows,
    keep_moving_gradient,
    map_loss,
    map_term,
    sum_per_scene,
    target_rows,
)
from policies.learned.plan_overlap import Separation, separation_term
from policies.pipeline.plan_set import PlanSet
from policies.riskflow.guidance_scene import (
    OPTIMIZERS,
    STEP_SIZES,
    GuidanceConfig,
    GuidanceResult,
    GuidanceScene,
)
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import DEFAULT_CONFIG, SPEED, clip_actions, rollout, rollout_with_vjp

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


class _Objective:
    """``(L_adv, L_map)`` of the ``A_c`` rows as a function of their residual ``u_c``.

    ``scene`` holds the rows of one scene, or of B scenes flattened to ``B * A`` rows
    (``frame`` (B, 3), the map a ``MapStack`` or shared); ``rows`` (C,) index them;
    ``target_xy`` is (J, T, 2), shared, or (C, J, T, 2) per row with ``target_valid``
    (C, J); ``scene_of_row`` (C,) the scene of each row (None: one scene);
    ``bystanders`` ``(O,)`` agents whose fixed plans the rows keep clear of and their
    scenes (``L_sep``; None: none).
    """

    def __init__(
        self,
        scene: GuidanceScene,
        rows: Tensor,
        target_xy: Tensor,
        normalizer: Normalizer,
        config: GuidanceConfig,
        dynamics: DynamicsConfig,
        target_valid: Tensor | None = None,
        scene_of_row: Tensor | None = None,
        bystanders: tuple[Tensor, Tensor] | None = None,
    ) -> None:
        zero = torch.zeros_like(scene.eps[:1, :1])
        self.std = normalizer.denormalize(zero + 1.0) - normalizer.denormalize(zero)
        self.offset = normalizer.denormalize(scene.eps[rows])  # a = offset + std * u_c
        self.state = scene.state[rows]
        self.target_xy, self.target_valid = target_xy, target_valid
        self.horizon, self.dynamics = config.resolved_horizon, dynamics
        self.map_term = map_term(scene, rows, scene.eps.shape[1], config, scene_of_row)
        self.lambda_sep = config.lambda_sep
        self.separation = separation_term(scene, rows, config, scene_of_row, *(bystanders or ()))
        attack_ego = config.target == Target.EGO
        self.accel_limit = HUMAN_ACCEL if attack_ego else math.inf
        self.yaw_rate_limit = HUMAN_YAW_RATE if attack_ego else math.inf
        # attacking the ego, the attacker keeps moving (guidance_losses.KEEP_MOVING)
        self.floor = self.state[:, SPEED].clamp(max=KEEP_MOVING) if attack_ego else None

    def bounds(self) -> tuple[Tensor, Tensor]:
        """(C, T, 2) lower and upper bounds of ``u_c`` that keep the actions inside the
        dynamics' accel and yaw-rate bounds (and, attacking the ego, within the human
        ``HUMAN_ACCEL`` and ``HUMAN_YAW_RATE``)."""
        dyn = self.dynamics
        accel_min = max(dyn.accel_min, -self.accel_limit)
        accel_max = min(dyn.accel_max, self.accel_limit)
        yaw_rate = min(dyn.yaw_rate_max, self.yaw_rate_limit)
        low = self.offset.new_tensor([accel_min, -yaw_rate])
        high = self.offset.new_tensor([accel_max, yaw_rate])
        return (low - self.offset) / self.std, (high - self.offset) / self.std

    def actions(self, u_c: Tensor) -> Tensor:
        """(C, T, 2) ``denorm(eps + u_c)`` [m/s^2, rad/s] (inside the bounds: ``u_c`` is
        kept there by the projection)."""
        return self.offset + self.std * u_c

    def __call__(self, u_c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(C, T, 4) trajectories, (C,) ``L_adv`` [m] and (C,) ``L_map`` [m^2] of each row
        (no gradient)."""
        trajectories = rollout(self.state, self.actions(u_c), self.dynamics)
        adv, _ = adversarial_rows(
            trajectories[..., :2], self.target_xy, self.horizon, self.target_valid, False
        )
        if self.map_term is None:
            return trajectories, adv, adv * 0.0
        return trajectories, adv, self.map_term.rows(trajectories)

    def gradient(self, u_c: Tensor, lambda_adv: float, lambda_map: float) -> tuple[Tensor, ...]:
        """``grad_u L`` (C, T, 2) of ``L = lambda_adv * L_adv + lambda_map * L_map``
        (plus ``lambda_sep * L_sep`` and, attacking the ego, the speed floor), and (C,)
        ``L_adv`` [m] and ``L_map`` [m^2] of each row.

        No autograd: the losses give their value and their gradient with respect to the
        trajectories in closed form (``adversarial_rows``, ``MapTerm.rows_and_gradient``),
        the rollout its vector-Jacobian product (``rollout_with_vjp``), and
        ``a = offset + std * u_c`` is a diagonal scale. Rows do not interact: each row's
        gradient is that of its own scene's loss.
        """
        # In bounds (the projection keeps them there): the rollout's clip is skipped.
        trajectories, vjp = rollout_with_vjp(
            self.state, self.actions(u_c), self.dynamics, clip=False
        )
        adv, d_xy = adversarial_rows(
            trajectories[..., :2], self.target_xy, self.horizon, self.target_valid
        )
        d_trajectories = torch.zeros_like(trajectories)
        d_trajectories[..., :2] = lambda_adv * d_xy
        if self.map_term is None:
            off_road = adv * 0.0
        else:
            off_road, d_map = self.map_term.rows_and_gradient(trajectories)
            d_trajectories.add_(d_map, alpha=lambda_map)
        if self.separation is not None:
            d_trajectories.add_(self.separation.gradient(trajectories), alpha=self.lambda_sep)
        if self.floor is not None:
            d_trajectories[..., SPEED] += keep_moving_gradient(
                trajectories[..., SPEED], self.floor, self.horizon
            )
        return vjp(d_trajectories) * self.std, adv, off_road


def guide(
    scene: GuidanceScene,
    controllable: Tensor,
    normalizer: Normalizer,
    config: GuidanceConfig | None = None,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> GuidanceResult:
    """Run ``K_g`` guidance steps on the ``A_c`` rows of ``scene.u0`` (module docstring).

    One scene, or B scenes in one loop (batched planning): every scene's ``A_c`` rows are
    the variables of one optimisation whose loss is the sum of the scenes' losses. Rows do
    not interact (each is pulled toward its own scene's targets, on its own map) and Adam
    is per coordinate, so each scene's plans are those of guiding it alone, to float
    rounding.

    Args:
        scene: the plans and the scene (one, or B with a leading axis).
        controllable: (A,) bool ``A_c`` ((B, A) for B scenes; absent agents and the ego
            are ignored).
        normalizer: action normalisation.
        config: guidance options.
        dynamics: time step and bounds.

    Returns:
        the :class:`GuidanceResult`; every row outside ``A_c`` equals the base plan.
    """
    config = config or GuidanceConfig()
    single = scene.eps.ndim == 3
    if scene.eps.ndim not in (3, 4):
        raise ValueError(f"scene.eps must be (A, T, 2) or (B, A, T, 2), got {scene.eps.shape}")
    if tuple(controllable.shape) != tuple(scene.agent_mask.shape):
        raise ValueError(
            f"controllable must have agent_mask's shape {tuple(scene.agent_mask.shape)}, "
            f"got {tuple(controllable.shape)}"
        )
    if single:
        tensors = {name: getattr(scene, name)[None] for name in PER_AGENT}
        scene = dataclasses.replace(scene, frame=scene.frame[None], **tensors)
        controllable = controllable[None]
    result = _guide_scenes(scene, controllable, normalizer, config, dynamics)
    if not single:
        return result
    return GuidanceResult(
        result.u[0], result.actions[0], result.trajectories[0], result.losses[:, 0]
    )


def _guide_scenes(
    scene: GuidanceScene,
    controllable: Tensor,
    normalizer: Normalizer,
    config: GuidanceConfig,
    dynamics: DynamicsConfig,
) -> GuidanceResult:
    """:func:`guide` of B scenes (leading axis on every tensor of ``scene``)."""
    num_scenes, num_agents = scene.agent_mask.shape
    guided = guided_rows(scene, controllable, config.target)
    rows, scene_of_row = guided.rows, guided.scene_of_row
    if rows.numel() == 0:  # nothing to guide: the base plans
        losses = scene.eps.new_zeros(config.steps + 1, num_scenes, 2)
        return GuidanceResult(scene.u0, scene.base_actions, scene.base_trajectories, losses)
    flat = flatten_scenes(scene)
    objective = _Objective(
        flat, rows, guided.target_xy, normalizer, config, dynamics, guided.target_valid,
        scene_of_row, (guided.bystanders, guided.scene_of_bystander),
    )  # fmt: skip

    with torch.no_grad():
        lower, upper = objective.bounds()
        u_c = torch.minimum(torch.maximum(flat.u0[rows], lower), upper)
    if compiled_plans.accepts(u_c, objective.map_term):  # the same loop, compiled
        u_c, trajectories_c, row_losses = compiled_plans.guidance_steps(
            objective, u_c, lower, upper, config
        )
    else:
        u_c, trajectories_c, row_losses = _steps(objective, u_c, lower, upper, config)
    with torch.no_grad():
        u = flat.u0.clone()
        u[rows] = u_c
        actions = flat.base_actions.clone()
        actions[rows] = clip_actions(objective.actions(u_c), dynamics)
        trajectories = flat.base_trajectories.clone()
        trajectories[rows] = trajectories_c  # rollout clips: the same as the clipped actions'
        losses = guided.per_scene(row_losses.transpose(0, 1), num_scenes).transpose(0, 1)
    lead = (num_scenes, num_agents)
    return GuidanceResult(
        u=u.reshape(*lead, *u.shape[1:]),
        actions=actions.reshape(*lead, *actions.shape[1:]),
        trajectories=trajectories.reshape(*lead, *trajectories.shape[1:]),
        losses=losses,
    )


def _steps(
    objective: _Objective, u_c: Tensor, lower: Tensor, upper: Tensor, config: GuidanceConfig
) -> tuple[Tensor, Tensor, Tensor]:
    """The guidance steps in torch (the reference of the compiled loop,
    :func:`policies.learned.compiled_plans.guidance_steps`): the guided ``u_c`` (C, T, 2),
    its rollout (C, T, 4) and (steps + 1, C, 2) ``(L_adv, L_map)`` of each row before each
    step and after the last."""
    step_size = config.resolved_step_size
    adam = Adam(u_c, step_size)
    history = []
    # Closed-form gradients: nothing to record, and inference mode skips autograd's
    # per-op bookkeeping (version counters) too; u_c leaves it only through copies.
    with torch.inference_mode():
        for _ in range(config.steps):
            grad, adv, off_road = objective.gradient(u_c, config.lambda_adv, config.lambda_map)
            history.append(torch.stack([adv, off_road], dim=-1))
            if config.optimizer == "gradient":
                grad = step_size * grad
            else:
                grad = adam.step(grad)
            u_c = torch.minimum(torch.maximum(u_c - grad, lower), upper)
    with torch.no_grad():
        trajectories_c, adv, off_road = objective(u_c)
        history.append(torch.stack([adv, off_road], dim=-1))
    return u_c, trajectories_c, torch.stack(history)


def guidance_scene(plans: PlanSet) -> GuidanceScene:
    """What the guidance of the ``A_c`` rows works on: the base plans and the scenes."""
    observed = plans.observed
    return GuidanceScene(
        eps=plans.eps,
        u0=plans.u,
        state=observed.scene.state,
        length=observed.batch.length,
        width=observed.batch.width,
        agent_mask=observed.scene.agent_mask,
        base_actions=plans.base_actions,
        base_trajectories=plans.base_trajectories,
        drivable_map=plans.drivable_map,
        frame=observed.frame_tensor(),
    )


def guide_outputs(policy: Any, plans: PlanSet) -> PlanSet:
    """The ``guide`` stage of :class:`~policies.riskflow.policy.RiskFlowAdversary`:
    output-space guidance (:func:`guide`) of the ``A_c`` rows of every scene, one loop
    for all."""
    result = guide(
        guidance_scene(plans), plans.controllable, policy.normalizer, policy.guidance,
        policy.dynamics,
    )  # fmt: skip
    return plans.replace(
        u=result.u, actions=result.actions, trajectories=result.trajectories, losses=result.losses
    )


guide_outputs.phase = "guidance"


__all__ = [
    "OPTIMIZERS",
    "STEP_SIZES",
    "Separation",
    "TARGETS",
    "GuidanceConfig",
    "GuidanceResult",
    "GuidanceScene",
    "adversarial_loss",
    "adversarial_value_and_gradient",
    "GuidedRows",
    "flatten_scenes",
    "guide",
    "guided_rows",
    "guidance_scene",
    "guide_outputs",
    "PER_AGENT",
    "map_loss",
]
