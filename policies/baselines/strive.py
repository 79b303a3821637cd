"""``StriveAdversary``: STRIVE-style latent optimisation through the one-step generator.

STRIVE (Rempe et al. 2022, "Generating Useful Accident-Prone Driving Scenarios via a
Learned Traffic Prior", CVPR) makes a scenario adversarial by optimising the *latent
codes* of a learned traffic model. Here the model is RiskFlow's MeanFlow generator and its
latent the input noise ``eps``: every planning cycle runs RiskFlow's pipeline (window,
encoder, base plans ``eps + u_theta(eps, 0, 1; C)``, TTC ranking of ``A_c``) and then,
instead of guiding the output ``u``, takes ``K_g`` steps on the ``A_c`` rows of ``eps``::

    eps_c <- step(grad_{eps_c} L),   L = lambda_adv L_adv + lambda_map L_map
                                          + lambda_prior ||eps_c||^2 / 2

each a forward and backward pass of the generator head (the scene context is computed
once). ``L_adv``, ``L_map``, their weights, targets, horizon and step rule are RiskFlow's
(:mod:`policies.riskflow.guidance`), so the comparison isolates latent against
output-space optimisation; the other vehicles keep their base plans bit for bit, and
``k = 0`` is the unguided generator exactly. docs/BASELINES.md ("STRIVE-style") maps each
part to the original, says what is simplified and why, and gives the measured effect and
cost.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from policies.learned.adam import Adam
from policies.learned.adversary_config import AdversaryConfig
from policies.learned.encoded_views import EncodedView, EncodedViews
from policies.learned.generator import RiskFlowGenerator
from policies.learned.guidance_losses import adversarial_loss, map_term, target_rows
from policies.learned.plan_buffer import PlanBufferPolicy
from policies.learned.sampler import base_velocity
from policies.riskflow.guidance import (
    GuidanceResult,
    GuidanceScene,
    PLAN_BLOCK,
    one_scene,
    plans_from_velocity,
)
from policies.riskflow.policy import RiskFlowAdversary
from riskflow_env.view import SceneView

DEFAULT_LAMBDA_PRIOR = 1.0  # weight of ||eps_c||^2 / 2 [per unit of normalised noise^2]


class StriveAdversary(RiskFlowAdversary):
    """STRIVE-style adversary for every non-ego vehicle (module docstring).

    Args:
        config: the shared options (:class:`~policies.learned.adversary_config.AdversaryConfig`:
            ``k``, ``target``, ``lambda_adv``, ``lambda_map``, ``seed``, ...; the same
            ``eps`` as ``RiskFlowAdversary`` with the same seed), or as keywords.
        lambda_prior: weight of the latent prior ``||eps_c||^2 / 2``, >= 0.
        generator: a MeanFlow ``RiskFlowGenerator`` (with ``normalizer``), ``"meanflow"``,
            or None (the shipped one, or ``checkpoint``'s); a diffusion generator is
            refused (no one-step latent to differentiate through).
        **options: ``RiskFlowAdversary``'s: ``guidance_steps`` (``K_g`` latent optimisation
            steps per cycle), ``step_size`` (Adam learning rate [normalised noise units
            per step], or ``gamma`` of plain steps), ``optimizer`` (``"adam"``:
            ``torch.optim.Adam`` on the latent, STRIVE's; ``"adam-plan"``: one second
            moment per latent row; ``"gradient"``: plain steps), ``normalizer``,
            ``checkpoint``, and the shared options as keywords.

    After each cycle: ``guidance_losses`` ((K_g + 1, 2): ``L_adv``, ``L_map`` before each
    step and after the last), ``prior_losses`` ((K_g + 1,): ``||eps_c||^2 / 2``) and
    ``latent`` ((A_w, T, 2): the optimised noise; ``noise`` is the drawn one).
    """

    overlay_prefix = "strive"

    def __init__(
        self,
        config: AdversaryConfig | None = None,
        *,
        lambda_prior: float = DEFAULT_LAMBDA_PRIOR,
        generator: RiskFlowGenerator | str | None = None,
        **options: Any,
    ) -> None:
        if not (isinstance(lambda_prior, (int, float)) and 0 <= lambda_prior < float("inf")):
            raise ValueError(f"lambda_prior must be a finite number >= 0, got {lambda_prior!r}")
        if generator == "diffusion" or "sampling_steps" in options:
            raise ValueError(_NOT_DIFFUSION)
        self.lambda_prior = float(lambda_prior)
        super().__init__(config, generator=generator, **options)
        if self.generator_kind != "meanflow":
            raise ValueError(_NOT_DIFFUSION)

    def _clear(self) -> None:
        super()._clear()
        self.prior_losses: np.ndarray | None = None
        self.latent: Tensor | None = None

    def _plan_cycles(self, scenes: Sequence[PlanBufferPolicy], views: Sequence[SceneView]) -> None:
        """Scene by scene: the latent optimisation keeps one scene's generator in the loop
        (batching it across scenes is left to do); each scene is the case B = 1 of
        ``RiskFlowAdversary``'s batched cycle."""
        if len(scenes) == 1:
            super()._plan_cycles(scenes, views)
            return
        for scene, view in zip(scenes, views, strict=True):
            scene._plan_cycles([scene], [view])

    def _guide(
        self, scene: GuidanceScene, controllable: Tensor, observed: EncodedViews
    ) -> GuidanceResult:
        """Batch of one (``_plan_cycles``): :meth:`_guide_scene` of it."""
        one = one_scene(scene, 0)
        result = self._guide_scene(one, controllable[0], observed.view(0))
        return GuidanceResult(
            result.u[None], result.actions[None], result.trajectories[None], result.losses[:, None]
        )

    def _guide_scene(
        self, scene: GuidanceScene, controllable: Tensor, observed: EncodedView
    ) -> GuidanceResult:
        """``K_g`` steps on the ``A_c`` rows of ``eps`` (module docstring)."""
        config = self.guidance
        present = scene.agent_mask.bool()
        mask = controllable.bool() & present
        mask[scene.ego] = False
        rows = torch.nonzero(mask).flatten()
        self.latent = scene.eps
        if rows.numel() == 0:  # nothing to optimise: the unguided generator, bit for bit
            self.prior_losses = np.zeros(config.steps + 1)
            losses = scene.eps.new_zeros(config.steps + 1, 2)
            return GuidanceResult(scene.u0, scene.base_actions, scene.base_trajectories, losses)
        objective = _LatentObjective(self, scene, observed, rows)
        eps_c = scene.eps[rows].clone().requires_grad_(True)
        if config.optimizer == "adam":
            optimizer = torch.optim.Adam([eps_c], lr=config.step_size)
        elif config.optimizer == "adam-plan":  # one second moment per latent row
            optimizer = _BlockAdam(eps_c, config.step_size, PLAN_BLOCK)
        else:
            optimizer = torch.optim.SGD([eps_c], lr=config.step_size)
        history = []
        for _ in range(config.steps):
            with torch.enable_grad():
                _, terms = objective(eps_c)
                loss = (
                    config.lambda_adv * terms[0]
                    + config.lambda_map * terms[1]
                    + self.lambda_prior * terms[2]
                )
                (eps_c.grad,) = torch.autograd.grad(loss, eps_c)
            history.append(terms.detach())
            optimizer.step()
        with torch.no_grad():
            (u_c, actions_c, trajectories_c), terms = objective(eps_c)
            history.append(terms)
            latent = scene.eps.clone()
            latent[rows] = eps_c
            u = scene.u0.clone()
            u[rows] = u_c
            actions = scene.base_actions.clone()
            actions[rows] = actions_c
            trajectories = scene.base_trajectories.clone()
            trajectories[rows] = trajectories_c
        history = torch.stack(history)
        self.latent = latent
        self.prior_losses = history[:, 2].cpu().numpy()
        return GuidanceResult(u, actions, trajectories, history[:, :2])


class _BlockAdam:
    """``optimizer.step()`` of :class:`~policies.learned.adam.Adam` with ``shared``
    dimensions on one leaf tensor (``optimizer="adam-plan"``)."""

    def __init__(self, variable: Tensor, learning_rate: float, shared: tuple[int, ...]) -> None:
        self.variable, self.adam = variable, Adam(variable, learning_rate, shared)

    def step(self) -> None:
        with torch.no_grad():
            self.variable -= self.adam.step(self.variable.grad)


_NOT_DIFFUSION = (
    "StriveAdversary optimises the latent of the one-step MeanFlow generator; a diffusion "
    "generator has no one-step latent map to differentiate through: use generator=None, "
    "'meanflow' or a MeanFlow checkpoint"
)


class _LatentObjective:
    """``(L_adv, L_map, ||eps_c||^2 / 2)`` of the ``A_c`` rows as a function of ``eps_c``."""

    def __init__(
        self, policy: StriveAdversary, scene: GuidanceScene, observed: EncodedView, rows: Tensor
    ) -> None:
        config = policy.guidance
        self.policy, self.scene, self.context, self.rows = policy, scene, observed.scene, rows
        controllable = torch.zeros_like(scene.agent_mask, dtype=torch.bool)
        controllable[rows] = True
        targets = target_rows(scene.agent_mask, controllable, scene.ego, config.target)
        self.target_xy = scene.base_trajectories[targets, :, :2].detach()
        self.map_term = map_term(scene, rows, scene.eps.shape[1], config)

    def __call__(self, eps_c: Tensor) -> tuple[tuple[Tensor, Tensor, Tensor], Tensor]:
        """``((u_c, actions_c, trajectories_c), (L_adv [m], L_map [m^2], prior))``."""
        policy, scene, rows = self.policy, self.scene, self.rows
        eps = scene.eps.index_put((rows,), eps_c)  # the other rows keep their noise
        u_c = base_velocity(policy.model, eps[None], self.context)[0, rows]
        actions, trajectories = plans_from_velocity(
            eps_c, u_c, scene.state[rows], scene.agent_mask[rows], policy.normalizer,
            policy.dynamics,
        )  # fmt: skip
        adv = adversarial_loss(trajectories[..., :2], self.target_xy, policy.guidance.horizon)
        off_road = adv * 0.0 if self.map_term is None else self.map_term(trajectories)
        prior = 0.5 * (eps_c * eps_c).sum()
        return (u_c, actions, trajectories), torch.stack([adv, off_road, prior])


__all__ = ["DEFAULT_LAMBDA_PRIOR", "StriveAdversary"]
