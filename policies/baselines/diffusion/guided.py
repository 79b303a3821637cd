"""Guided reverse chains: CTG-, CTG++- and CCDiff-style guidance with RiskFlow's losses.

All three bend the plans of a controllable set ``A_c`` at *every* denoising level,
minimising RiskFlow's own ``L = lambda_adv L_adv + lambda_map L_map + lambda_sep L_sep``
(:mod:`policies.learned.guidance_losses`; definitions, signs and weights in
:mod:`policies.riskflow.guidance`; ``L_sep``, on by default as for RiskFlow and
STRIVE-style, is not in the original methods: ``lambda_sep = 0`` drops it), so that only
the guidance mechanism differs:

* ``gradient="mean"`` (**CTG**, Zhong et al. 2023, "Guided Conditional Diffusion for
  Controllable Traffic Simulation", sec. 4.2): the transition mean ``mu`` of the ``A_c``
  rows is read as a plan, rolled through the unicycle (``dynamics.rollout``), and moved
  ``inner_steps`` times against ``grad_mu L(rollout(denorm(mu)))``; no network gradient.
* ``gradient="clean"`` (**CTG++**, Zhong et al. 2023, "Language-Guided Traffic Simulation
  via Scene-Level Diffusion", sec. 4.3): the loss is taken on the predicted clean plan
  ``x0_hat(x_k)`` and differentiated *through the denoiser* to the noisy sample,
  ``grad_{x_k} L(rollout(denorm(x0_hat(x_k))))``; the ``A_c`` rows of ``mu`` move against
  it (one gradient per level: each needs a backward pass through the network).
* **CCDiff** (Lin et al. 2025, "Causal Composition Diffusion Model for Closed-loop Traffic
  Generation") is CTG's mean guidance on the ``A_c`` chosen by the TTC causal ranking
  (:mod:`policies.learned.ranking`); CTG and CTG++ take the ``K`` vehicles nearest the
  ego (they have no notion of criticality). The choice of ``A_c`` is the policy's.

Step: each gradient is normalised per agent (divided by its RMS over the plan) and
scaled by ``step_size`` [normalised action units], the diffusion analogue of RiskFlow's
Adam step: a bounded move per step, the same in every scene (raw gradients scale with
``lambda``, speed and ``(T - t)^2``). Only ``A_c`` rows move.

``anchor=True`` (default): everyone else follows the unguided chain of the same noise,
bit for bit: the chain is run once without guidance (the base plans, as RiskFlow's),
then again with guidance, its non-``A_c`` rows replaced by the base chain's at every
level (inpainting). So guided vehicles react to the others' actual plans through the
scene-level denoiser, the others are unaffected, as with RiskFlow, and ``L_adv``'s
targets are the base plans (detached), RiskFlow's targets; guidance doubles the
denoiser passes. ``anchor=False``: one chain, the cost of unguided sampling (plus the
guidance); the others are denoised jointly with the guided rows (they react to them,
as in CTG++'s scene-level sampling), ``L_adv``'s targets are their current clean
estimates ``x0_hat`` at each level, and there are no separate base plans.

``L_sep`` is RiskFlow's: between the guided rows, and, anchored with target ``"ego"``,
between the attacker and the bystanders (the present vehicles neither guided nor a
target), whose base plans are fixed; unanchored, the bystanders' plans move with the chain
and only the guided rows are kept apart.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from policies.baselines.diffusion.model import DiffusionDenoiser
from policies.baselines.diffusion.sampling import (
    Levels,
    denoise_step,
    reverse_chain,
)
from policies.learned.data import Normalizer
from policies.learned.encoder import SceneContext
from policies.learned.guidance_losses import (
    ObjectiveConfig,
    adversarial_rows,
    bystander_rows,
    map_term,
    sum_per_scene,
    target_rows,
)
from policies.learned.plan_overlap import separation_term
from policies.learned.sampler import decode_plans
from policies.pipeline.stages import stand_still
from riskflow_env._array import attach_gradient
from riskflow_env.config import DynamicsConfig, is_integer
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout
from riskflow_env.maps import DrivableMap, MapStack

GRADIENTS = ("mean", "clean")
PER_AGENT = ("state", "length", "width", "agent_mask")  # SceneGeometry's (B, A) fields


@dataclass(frozen=True)
class DiffusionGuidanceConfig(ObjectiveConfig):
    """Options of diffusion guidance (module docstring): the shared objective's
    (:class:`~policies.learned.guidance_losses.ObjectiveConfig`: ``lambda_adv``,
    ``lambda_map``, ``horizon``, ``target``, ``map_margin``, ``map_decay``,
    ``lambda_sep``) and these.

    Attributes:
        gradient: ``"mean"`` (CTG, CCDiff) or ``"clean"`` (CTG++).
        inner_steps: gradient steps per level (``"mean"`` only; ``"clean"`` takes 1).
        step_size: per-agent RMS of one step [normalised action units].
        anchor: the others follow the unguided chain (module docstring).
    """

    gradient: str = "mean"
    inner_steps: int = 1
    step_size: float = 0.1
    anchor: bool = True

    def checks(self) -> list[tuple[bool, str]]:
        """The objective's rules and the sampler's."""
        inner_ok = is_integer(self.inner_steps) and self.inner_steps >= 1
        return super().checks() + [
            (self.gradient in GRADIENTS, f"gradient must be one of {GRADIENTS}"),
            (inner_ok, "inner_steps must be >= 1"),
            (
                self.gradient == "mean" or self.inner_steps == 1,
                "gradient 'clean' takes inner_steps 1",
            ),
            (math.isfinite(self.step_size) and self.step_size > 0, "step_size must be > 0"),
        ]


@dataclass(frozen=True)
class SceneGeometry:
    """What the losses need about one scene (torch, scene frame), or about B scenes
    (batched planning: a leading B axis on every per-agent tensor, agents padded to A).

    Attributes:
        state: (A, 4) current states (x, y [m], v [m/s], psi [rad]); (B, A, 4).
        length: (A,) [m]; (B, A).
        width: (A,) [m]; (B, A).
        agent_mask: (A,) bool agents present (False on padding); (B, A).
        drivable_map: the map (world frame); for B scenes a
            :class:`~riskflow_env.maps.MapStack` of their maps in scene order, or one map
            they share; None drops ``L_map``.
        frame: (3,) world pose (x [m], y [m], psi [rad]) of the scene frame; (B, 3).
        ego: slot of the ego (never guided; in every scene).
        standing: (A,) bool vehicles that stand still (done: zero actions, current pose at
            speed 0; never guided); (B, A); None: none.
    """

    state: Tensor
    length: Tensor
    width: Tensor
    agent_mask: Tensor
    drivable_map: DrivableMap | MapStack | None
    frame: Tensor
    ego: int = 0
    standing: Tensor | None = None

    def batched(self) -> SceneGeometry:
        """The geometry with a leading B axis (B = 1 for one scene)."""
        if self.state.ndim == 3:
            return self
        standing = None if self.standing is None else self.standing[None]
        fields = {name: getattr(self, name)[None] for name in PER_AGENT}
        return dataclasses.replace(self, **fields, frame=self.frame[None], standing=standing)


@dataclass(frozen=True)
class GuidedPlans:
    """``actions`` (A, T, 2), ``trajectories`` (A, T, 4) (base plans outside ``A_c`` when
    anchored), the unguided ``base_actions`` / ``base_trajectories`` (the plans themselves
    without ``anchor``), and ``losses`` (N, 2): ``(L_adv [m], L_map [m^2])`` at each
    gradient evaluation and, last, of the final plans. For B scenes: (B, A, ...) and
    losses (N, B, 2), each scene's own."""

    actions: Tensor
    trajectories: Tensor
    base_actions: Tensor
    base_trajectories: Tensor
    losses: Tensor


class _Objective:
    """``(L, L_adv, L_map)`` of the ``A_c`` rows (flat indices of B scenes' agents) as a
    function of their normalised actions: ``L`` a scalar (summed over the rows: each row's
    gradient is its own scene's), ``L_adv`` and ``L_map`` summed per scene, (B,) each
    (``L_sep`` enters ``L`` through its gradient only; its value is not recorded)."""

    def __init__(
        self, geometry, rows, scene_of_row, normalizer, config, dynamics, steps, bystanders=None
    ):
        flat = dataclasses.replace(
            geometry, **{name: getattr(geometry, name).flatten(0, 1) for name in PER_AGENT}
        )
        self.state, self.scene_of_row = flat.state[rows], scene_of_row
        self.num_scenes = geometry.state.shape[0]
        self.normalizer, self.config, self.dynamics = normalizer, config, dynamics
        self.map_term = map_term(flat, rows, steps, config, scene_of_row)
        if bystanders is None:  # the guided rows among themselves
            self.separation = separation_term(flat, rows, config, scene_of_row)
        else:  # (indices, their scenes, the (B, A, T, 4) base plans they keep)
            fixed = _Boxes(flat.length, flat.width, bystanders[2].flatten(0, 1))
            self.separation = separation_term(fixed, rows, config, scene_of_row, *bystanders[:2])

    def __call__(self, x_c: Tensor, target_xy: Tensor, target_valid: Tensor):
        trajectories = rollout(self.state, self.normalizer.denormalize(x_c), self.dynamics)
        xy = trajectories[..., :2]
        config = self.config
        adv_rows, gradient = adversarial_rows(xy, target_xy, config.resolved_horizon, target_valid)
        adv = attach_gradient(adv_rows.sum(), xy, gradient, axis=None)
        if self.map_term is None:
            off_rows, off_road = torch.zeros_like(adv_rows), adv * 0.0
        else:
            off_rows, gradient = self.map_term.rows_and_gradient(trajectories)
            off_road = attach_gradient(off_rows.sum(), trajectories, gradient, axis=None)
        loss = self.config.lambda_adv * adv + self.config.lambda_map * off_road
        if self.separation is not None:
            d_sep = self.separation.gradient(trajectories)
            loss = loss + attach_gradient(
                adv.new_zeros(()), trajectories, self.config.lambda_sep * d_sep, axis=None
            )
        return loss, self._per_scene(adv_rows), self._per_scene(off_rows)

    def _per_scene(self, values: Tensor) -> Tensor:
        return sum_per_scene(values.detach(), self.scene_of_row, self.num_scenes)


@dataclass(frozen=True)
class _Boxes:
    """What :func:`separation_term` reads of a scene: (N,) sizes and (N, T, 4) fixed plans."""

    length: Tensor
    width: Tensor
    base_trajectories: Tensor


def _step(grad: Tensor, step_size: float) -> Tensor:
    """``step_size * grad / rms(grad)`` per agent (row); 0 where the gradient is 0."""
    rms = grad.pow(2).mean(dim=(-2, -1), keepdim=True).sqrt()
    return step_size * grad / rms.clamp(min=1e-12)


def guided_sample(
    denoiser: DiffusionDenoiser,
    scene: SceneContext,
    noise: Tensor,
    levels: Levels,
    geometry: SceneGeometry,
    controllable: Tensor,
    normalizer: Normalizer,
    config: DiffusionGuidanceConfig | None = None,
    eta: float = 1.0,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
    on_base_done: Callable[[], object] | None = None,
) -> GuidedPlans:
    """Base chain, then the guided chain of the ``A_c`` rows (module docstring), for one
    scene or B scenes at once (batched planning: one denoiser pass per level for all of
    them, each row pulled toward its own scene's targets; each scene gets the plans it
    gets alone, to float rounding).

    Args:
        denoiser: the denoiser.
        scene: ``denoiser.encode(batch)`` of one scene (``B = 1``) or of B scenes.
        noise: ``(len(levels) + 1, B, A, T, 2)`` (``sampling.chain_noise``).
        levels: the chain's transitions (``denoiser.schedule.levels(S)``).
        geometry: the scene(s) for the losses: (A, ...) tensors for one scene (the
            result's tensors are then (A, ...)), (B, A, ...) for B scenes.
        controllable: ``A_c``, (A,) bool, or (B, A); absent agents and the ego are ignored.
        normalizer: action normalisation.
        config: guidance options.
        eta: DDIM stochasticity (1 with all levels: DDPM).
        dynamics: time step and bounds.
        on_base_done: called when the base chain is done (timing).
    """
    config = config or DiffusionGuidanceConfig()
    single = geometry.state.ndim == 2
    geometry = geometry.batched()
    controllable = controllable.reshape(geometry.agent_mask.shape)
    present = geometry.agent_mask.bool()
    standing = torch.zeros_like(present) if geometry.standing is None else geometry.standing
    standing = standing.bool()
    mask = controllable.bool() & present & ~standing
    mask[:, geometry.ego] = False
    rows = torch.nonzero(mask.flatten()).flatten()  # flat (scene, agent) indices
    scene_of_row = torch.div(rows, mask.shape[1], rounding_mode="floor")
    targets = target_rows(present, mask, geometry.ego, config.target)  # (B, A)
    target_valid = targets[scene_of_row]

    def plans(x0: Tensor) -> tuple[Tensor, Tensor]:
        actions, trajectories = decode_plans(
            x0, geometry.state, geometry.agent_mask, normalizer, dynamics
        )
        stand_still(actions, trajectories, geometry.state, standing)
        return actions, trajectories

    def targets_of(trajectories: Tensor) -> Tensor:  # (C, A, T, 2): each row's scene
        return trajectories[..., :2][scene_of_row]

    def shaped(plans: GuidedPlans) -> GuidedPlans:
        if not single:
            return plans
        losses = plans.losses[:, 0]
        fields = ("actions", "trajectories", "base_actions", "base_trajectories")
        return dataclasses.replace(
            plans, **{name: getattr(plans, name)[0] for name in fields}, losses=losses
        )

    path = None
    if config.anchor or rows.numel() == 0:
        path = reverse_chain(denoiser, scene, noise, levels, eta)
        base_actions, base_trajectories = plans(path[-1])
        target_xy = targets_of(base_trajectories)
    if on_base_done is not None:
        on_base_done()
    if rows.numel() == 0:
        empty = base_actions.new_zeros(0, mask.shape[0], 2)
        return shaped(
            GuidedPlans(base_actions, base_trajectories, base_actions, base_trajectories, empty)
        )
    bystanders = None
    if path is not None:  # anchored: the others keep their base plans (module docstring)
        standby, of_scene = bystander_rows(present, mask, targets)
        if standby.numel():
            bystanders = (standby, of_scene, base_trajectories)
    objective = _Objective(
        geometry, rows, scene_of_row, normalizer, config, dynamics, noise.shape[-2], bystanders
    )
    history, x = [], noise[0]

    def flat(tensor: Tensor) -> Tensor:  # (B, A, ...) -> (B * A, ...), a view (writable)
        return tensor.view(-1, *tensor.shape[2:])

    for index, (k, k_prev) in enumerate(levels):
        if config.gradient == "clean":
            with torch.enable_grad():
                x_in = x.detach().requires_grad_(True)
                x0_hat, eps_hat = denoiser(x_in, k, scene, clip=True)
                if path is None:
                    target_xy = targets_of(plans(x0_hat.detach())[1])
                loss, adv, off_road = objective(flat(x0_hat)[rows], target_xy, target_valid)
                (grad,) = torch.autograd.grad(loss, x_in)
            history.append(torch.stack([adv, off_road], dim=-1))
            with torch.no_grad():
                x0_hat, eps_hat = x0_hat.detach(), eps_hat.detach()
                mean, sigma = denoiser.schedule.reverse_moments(x0_hat, eps_hat, k, k_prev, eta)
                flat(mean)[rows] -= _step(flat(grad)[rows], config.step_size)
        else:
            with torch.no_grad():
                x0_hat, _, mean, sigma = denoise_step(denoiser, x, k, k_prev, eta, scene)
                if path is None:
                    target_xy = targets_of(plans(x0_hat)[1])
            mean_c = flat(mean)[rows]
            for _ in range(config.inner_steps):
                with torch.enable_grad():
                    mean_c = mean_c.detach().requires_grad_(True)
                    loss, adv, off_road = objective(mean_c, target_xy, target_valid)
                    (grad,) = torch.autograd.grad(loss, mean_c)
                history.append(torch.stack([adv, off_road], dim=-1))
                mean_c = mean_c.detach() - _step(grad, config.step_size)
            flat(mean)[rows] = mean_c
        with torch.no_grad():
            x = mean + sigma * noise[index + 1]
            if path is not None:  # inpainting: the others keep the base chain
                x = torch.where(mask[..., None, None], x, path[index + 1])
    with torch.no_grad():
        guided_actions, guided_trajectories = plans(x)
        if path is None:
            actions, trajectories = guided_actions, guided_trajectories
            base_actions, base_trajectories = actions, trajectories
            target_xy = targets_of(trajectories)
        else:
            actions, trajectories = base_actions.clone(), base_trajectories.clone()
            flat(actions)[rows] = flat(guided_actions)[rows]
            flat(trajectories)[rows] = flat(guided_trajectories)[rows]
        _, adv, off_road = objective(flat(x)[rows], target_xy, target_valid)
        history.append(torch.stack([adv, off_road], dim=-1))
    losses = torch.stack(history)  # (N, B, 2)
    return shaped(GuidedPlans(actions, trajectories, base_actions, base_trajectories, losses))


__all__ = ["GRADIENTS", "DiffusionGuidanceConfig", "GuidedPlans", "SceneGeometry", "guided_sample"]
