"""``StriveAdversary``: STRIVE-style latent optimisation through the one-step generator.

STRIVE (Rempe et al. 2022, "Generating Useful Accident-Prone Driving Scenarios via a
Learned Traffic Prior", CVPR) makes a scenario adversarial by optimising the *latent
codes* of a learned traffic model. Here the model is RiskFlow's MeanFlow generator and its
latent the input noise ``eps``: every planning cycle runs RiskFlow's pipeline (window,
encoder, base plans ``eps + u_theta(eps, 0, 1; C)``, TTC ranking of ``A_c``) and then,
instead of guiding the output ``u``, takes ``K_g`` steps on the ``A_c`` rows of ``eps``::

    eps_c <- step(grad_{eps_c} L),   L = lambda_adv L_adv + lambda_map L_map
                                          + lambda_prior ||eps_c||^2 / 2 (+ lambda_sep L_sep)

each a forward and backward pass of the generator head (the scene context is computed
once). ``L_adv``, ``L_map``, their weights, targets, horizon and step rule are RiskFlow's
(:mod:`policies.riskflow.guidance`), and so is ``A_c`` (with target ``"ego"`` one
attacker at a time, :func:`policies.learned.ranking.ego_attacker`) and the optional
``L_sep`` between the guided vehicles, and with target ``"ego"`` between the attacker and
the bystanders' fixed plans (``lambda_sep``; the original penalises collisions between
agents that are not the attacker and its target too), so the comparison isolates latent against
output-space optimisation; the other vehicles keep their base plans bit for bit, and
``k = 0`` is the unguided generator exactly. docs/how-to/baselines.md ("STRIVE-style") maps each
part to the original, says what is simplified and why, and gives the measured effect and
cost.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from policies.learned.adversary_config import AdversaryConfig
from policies.learned.data import Normalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.guidance_losses import adversarial_rows, map_term
from policies.learned.plan_overlap import separation_term
from policies.learned.sampler import base_velocity, decode_plans
from policies.pipeline.plan_set import PlanSet
from policies.riskflow.guidance import (
    GuidanceConfig,
    GuidanceScene,
    GuidedRows,
    flatten_scenes,
    guidance_scene,
    guided_rows,
)
from policies.riskflow.policy import PHASES, GeneratorPolicy
from riskflow_env._array import attach_gradient
from riskflow_env.config import is_number, plain_number

DEFAULT_LAMBDA_PRIOR = 1.0  # weight of ||eps_c||^2 / 2 [per unit of normalised noise^2]
# Adam's learning rate on the latent [normalised noise units per step]: STRIVE-style's best
# of 0.03 / 0.1 / 0.3 at every K (docs/explanation/results.md section 4), for either target
# (RiskFlow's default follows the target: policies.riskflow.guidance.STEP_SIZES)
DEFAULT_STEP_SIZE = 0.1


def optimise_latent(policy: StriveAdversary, plans: PlanSet) -> PlanSet:
    """The ``guide`` stage of STRIVE-style: ``K_g`` steps on the ``A_c`` rows of ``eps``
    of B scenes at once (module docstring). The loss is the sum of the scenes' losses and
    rows of different scenes do not interact (the generator attends within a scene, each
    row has its own scene's targets and map, Adam is per coordinate), so each scene's
    latent is the one it would get alone, to float rounding. Each scene keeps its
    optimised ``latent`` and its ``prior_losses`` (``PlannerState.extras``)."""
    config = policy.guidance
    scene = guidance_scene(plans)
    num_scenes, num_agents = scene.agent_mask.shape
    counts = plans.observed.counts
    guided = guided_rows(scene, plans.controllable, config.target)
    rows = guided.rows
    if rows.numel() == 0:  # nothing to optimise: the unguided generator, bit for bit
        losses = scene.eps.new_zeros(config.steps + 1, num_scenes, 2)
        extras = _extras(scene.eps, None, counts, config.steps + 1)
        return plans.replace(
            actions=scene.base_actions, trajectories=scene.base_trajectories, losses=losses,
            extras=extras,
        )  # fmt: skip
    objective = _LatentObjective(policy, scene, plans.observed.scene, guided)
    eps_c = scene.eps.flatten(0, 1)[rows].clone().requires_grad_(True)
    if config.optimizer == "adam":
        optimizer = torch.optim.Adam([eps_c], lr=config.resolved_step_size)
    else:
        optimizer = torch.optim.SGD([eps_c], lr=config.resolved_step_size)

    history = []
    for _ in range(config.steps):
        with torch.enable_grad():
            _, terms = objective(eps_c)
            adv, off_road, prior, separation = terms.sum(dim=0)
            loss = config.lambda_adv * adv + config.lambda_map * off_road
            loss = loss + policy.lambda_prior * prior + config.lambda_sep * separation
            (eps_c.grad,) = torch.autograd.grad(loss, eps_c)
        history.append(guided.per_scene(terms.detach(), num_scenes))
        optimizer.step()
    with torch.no_grad():
        (u_c, actions_c, trajectories_c), terms = objective(eps_c)
        history.append(guided.per_scene(terms, num_scenes))
        lead = (num_scenes, num_agents)
        latent, u = scene.eps.flatten(0, 1).clone(), scene.u0.flatten(0, 1).clone()
        actions = scene.base_actions.flatten(0, 1).clone()
        trajectories = scene.base_trajectories.flatten(0, 1).clone()
        latent[rows], u[rows], actions[rows], trajectories[rows] = (
            eps_c,
            u_c,
            actions_c,
            trajectories_c,
        )
    history = torch.stack(history)  # (K_g + 1, B, 4)
    extras = _extras(latent.reshape(scene.eps.shape), history[..., 2], counts, config.steps + 1)
    return plans.replace(
        u=u.reshape(*lead, *u.shape[1:]),
        actions=actions.reshape(*lead, *actions.shape[1:]),
        trajectories=trajectories.reshape(*lead, *trajectories.shape[1:]),
        losses=history[..., :2],
        extras=extras,
    )


optimise_latent.phase = "guidance"


def _extras(latent: Tensor, prior: Tensor | None, counts: Sequence[int], steps: int) -> list:
    """Each scene's optimised ``latent`` (its ``count`` rows) and ``prior_losses``
    ((K_g + 1,); zeros for None)."""
    return [
        {
            "latent": latent[index, :count].clone(),
            "prior_losses": np.zeros(steps) if prior is None else prior[:, index].cpu().numpy(),
        }
        for index, count in enumerate(counts)
    ]


class StriveAdversary(GeneratorPolicy):
    """STRIVE-style adversary for every non-ego vehicle (module docstring).

    Args:
        config: the shared options (:class:`~policies.learned.adversary_config.AdversaryConfig`:
            ``k``, ``target``, ``lambda_adv``, ``lambda_map``, ``seed``, ...; the same
            ``eps`` as ``RiskFlowAdversary`` with the same seed), or as keywords.
        lambda_prior: weight of the latent prior ``||eps_c||^2 / 2``, >= 0.
        step_size: Adam's learning rate [normalised noise units per step] (default 0.1,
            this method's best, docs/explanation/results.md section 4), or ``gamma`` of plain steps.
        guidance_steps: ``K_g`` latent optimisation steps per cycle.
        optimizer: ``"adam"`` (``torch.optim.Adam`` on the latent, STRIVE's) or
            ``"gradient"`` (plain steps).
        lambda_sep: weight of the separation of the guided vehicles (as RiskFlow's).
        generator: a MeanFlow ``RiskFlowGenerator`` (with ``normalizer``), ``"meanflow"``,
            or None (the shipped one, or ``checkpoint``'s); a diffusion generator is
            refused (no one-step latent to differentiate through).
        normalizer, checkpoint, avoid_steps, avoid_step_size: as ``RiskFlowAdversary``'s.
        **options: the shared options as keywords.

    After each cycle: ``guidance_losses`` ((K_g + 1, 2): ``L_adv``, ``L_map`` before each
    step and after the last), ``prior_losses`` ((K_g + 1,): ``||eps_c||^2 / 2``) and
    ``latent`` ((A_w, T, 2): the optimised noise; ``noise`` is the drawn one).
    """

    overlay_prefix = "strive"
    phases = PHASES

    def __init__(
        self,
        config: AdversaryConfig | None = None,
        *,
        lambda_prior: float = DEFAULT_LAMBDA_PRIOR,
        step_size: float = DEFAULT_STEP_SIZE,
        guidance_steps: int = 30,
        optimizer: str = GuidanceConfig.optimizer,
        lambda_sep: float = GuidanceConfig.lambda_sep,
        generator: RiskFlowGenerator | str | None = None,
        normalizer: Normalizer | None = None,
        checkpoint: str | os.PathLike | None = None,
        avoid_steps: int | None = None,
        avoid_step_size: float = 0.1,
        **options: Any,
    ) -> None:
        if not (is_number(lambda_prior) and 0 <= lambda_prior < float("inf")):
            raise ValueError(f"lambda_prior must be a finite number >= 0, got {lambda_prior!r}")
        if generator == "diffusion" or "sampling_steps" in options:
            raise ValueError(_NOT_DIFFUSION)
        config = AdversaryConfig.resolve(config, options, type(self).__name__)
        self.lambda_prior = float(plain_number(lambda_prior))
        guidance = GuidanceConfig.of(config, guidance_steps, step_size, optimizer, lambda_sep)
        super().__init__(
            config, guidance, optimise_latent, generator, normalizer, checkpoint, None,
            avoid_steps, avoid_step_size,
        )  # fmt: skip
        if self.generator_kind != "meanflow":
            raise ValueError(_NOT_DIFFUSION)

    latent = property(lambda self: self.state.extras.get("latent"), doc="(A_w, T, 2) latent")
    prior_losses = property(
        lambda self: self.state.extras.get("prior_losses"), doc="(K_g + 1,) prior losses"
    )


_NOT_DIFFUSION = (
    "StriveAdversary optimises the latent of the one-step MeanFlow generator; a diffusion "
    "generator has no one-step latent map to differentiate through: use generator=None, "
    "'meanflow' or a MeanFlow checkpoint"
)


class _LatentObjective:
    """``(L_adv, L_map, ||eps_c||^2 / 2)`` of each ``A_c`` row as a function of ``eps_c``,
    for the rows of B scenes (``rows`` index the flattened ``B * A`` agents; each row is
    pulled toward its own scene's targets, on its own scene's map)."""

    def __init__(
        self,
        policy: StriveAdversary,
        scene: GuidanceScene,
        context: Any,
        guided: GuidedRows,
    ) -> None:
        config, rows = policy.guidance, guided.rows
        self.policy, self.context, self.rows = policy, context, rows
        self.shape = scene.eps.shape
        self.target_xy, self.target_valid = guided.target_xy, guided.target_valid
        flat = flatten_scenes(scene)
        self.eps, self.state, self.agent_mask = flat.eps, flat.state[rows], flat.agent_mask[rows]
        self.map_term = map_term(flat, rows, scene.eps.shape[2], config, guided.scene_of_row)
        self.separation = separation_term(
            flat, rows, config, guided.scene_of_row, guided.bystanders, guided.scene_of_bystander
        )

    def __call__(self, eps_c: Tensor) -> tuple[tuple[Tensor, Tensor, Tensor], Tensor]:
        """``((u_c, actions_c, trajectories_c), terms)``, ``terms`` (C, 4): each row's
        ``L_adv`` [m], ``L_map`` [m^2], ``||eps_c||^2 / 2`` and a zero that carries the
        gradient of ``L_sep`` (its value is not recorded), differentiable with respect to
        ``eps_c`` (the losses' gradients in closed form, attached)."""
        policy, rows = self.policy, self.rows
        eps = self.eps.index_put((rows,), eps_c).reshape(self.shape)  # the others keep theirs
        u_c = base_velocity(policy.model, eps, self.context).flatten(0, 1)[rows]
        actions, trajectories = decode_plans(
            eps_c + u_c, self.state, self.agent_mask, policy.normalizer, policy.dynamics
        )
        xy = trajectories[..., :2]
        guidance = policy.guidance
        adv, d_xy = adversarial_rows(
            xy, self.target_xy, guidance.resolved_horizon, self.target_valid
        )
        adv = attach_gradient(adv, xy, d_xy, axis=(-2, -1))
        if self.map_term is None:
            off_road = adv * 0.0
        else:
            off_road, d_map = self.map_term.rows_and_gradient(trajectories.detach())
            off_road = attach_gradient(off_road, trajectories, d_map, axis=(-2, -1))
        prior = 0.5 * (eps_c * eps_c).sum(dim=(-2, -1))
        separation = prior * 0.0
        if self.separation is not None:
            d_sep = self.separation.gradient(trajectories)
            separation = attach_gradient(separation.detach(), trajectories, d_sep, (-2, -1))
        terms = torch.stack([adv, off_road, prior, separation], dim=-1)
        return (u_c, actions, trajectories), terms


__all__ = ["DEFAULT_LAMBDA_PRIOR", "DEFAULT_STEP_SIZE", "StriveAdversary"]
