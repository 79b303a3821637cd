"""``StriveAdversary``: STRIVE-style latent optimisation through the one-step generator.

STRIVE (Rempe et al. 2022, "Generating Useful Accident-Prone Driving Scenarios via a
Learned Traffic Prior", CVPR) makes a scenario adversarial by optimising the *latent
codes* of a learned traffic model, so that the decoded scene stays likely under the
model. Here the learned traffic model is RiskFlow's MeanFlow generator and its latent is
the input noise ``eps`` (standard normal, one (T, 2) block per agent): every planning
cycle runs RiskFlow's pipeline (:class:`~policies.riskflow.policy.RiskFlowAdversary`:
window, encoder, base plans ``eps + u_theta(eps, 0, 1; C)``, TTC causal ranking of the
top-``K`` ``A_c``) and then, instead of guiding the output ``u``, takes ``K_g`` steps on
the ``A_c`` rows of ``eps``::

    eps_c <- step(grad_{eps_c} L),   L = lambda_adv L_adv + lambda_map L_map
                                          + lambda_prior ||eps_c||^2 / 2,
    plans = clip(denorm(eps + u_theta(eps, 0, 1; C)))   (eps with its A_c rows = eps_c)

so each step is a forward *and backward* pass of the generator head over the whole scene
(the scene context ``C`` is computed once, without gradients). ``L_adv``, ``L_map``,
their weights, sign convention (``lambda_adv > 0`` is more adversarial), targets (base
plans of everyone outside ``A_c``, detached; ``target="ego"``: the ego's), horizon and
the step rule (Adam with learning rate ``step_size``, or plain steps) are RiskFlow's
(:mod:`policies.riskflow.guidance`), so a comparison with RiskFlow isolates *latent*
against *output-space* optimisation. ``||eps_c||^2 / 2`` is ``-log N(eps_c; 0, I)`` up to a
constant: the prior term of STRIVE, exact for this latent.

**Who changes.** The generator decodes the scene jointly, so moving ``eps_c`` also moves
the decoded plans of the other vehicles (they react through social attention; STRIVE
re-decodes the whole scene). Here only the ``A_c`` rows of the decoded plan are used; the
other vehicles keep their base plans bit for bit (their ``eps`` is fixed and they are not
re-decoded), as with RiskFlow and the diffusion baselines (CCDiff-style inpainting).
Reasons: the comparison stays on the one difference under test; STRIVE holds its other
agents plausible with further terms (latents near their initial values, no collisions
among them or with the map) that are not part of this comparison's objective; and every
vehicle reacts to the others at the next re-plan (0.5 s), as with RiskFlow. ``k = 0`` (or
no eligible vehicle) gives exactly the unguided generator.

**Mapping to the original, and what is simplified**

========================================  =============================================
STRIVE                                    here
========================================  =============================================
CVAE traffic model: graph network         the MeanFlow generator (scene encoder +
encoder/decoder, learned conditional      social-attention head); latent = input noise
prior ``p(z | scene)`` per agent          ``eps``, prior ``N(0, I)``
adversarial term: planner collides with   RiskFlow's ``L_adv`` (distance to the nearest
an adversary, softly chosen among agents  target) on the TTC-ranked top-``K`` ``A_c``
prior term ``-log p(z)``, weighted        ``lambda_prior ||eps_c||^2 / 2``
per attacker / other agent
latents of all agents optimised; others   only ``A_c``'s latents; others hold their base
kept near their initial latents, no       plans (above)
collisions among them
environment-collision term                RiskFlow's ``L_map`` (SDF footprint penalty)
Adam, 200 iterations, lr 0.05, offline    ``K_g = 30`` steps per 0.5 s cycle, closed loop
rule-based planner in the loop, then a    no separate solution-optimisation stage, no
solution-optimisation stage and a         planner in the optimisation, no filtering
feasibility filter
========================================  =============================================

Actions are clipped to the dynamics bounds after decoding (as for every generator
sample); a latent that decodes beyond a bound gets no gradient along it (the output-space
guidance projects instead). Cost: ``K_g`` generator forward+backward passes per cycle
(RiskFlow: ``K_g`` rollouts of the ``A_c`` rows only); timings in docs/BASELINES.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from policies.learned.adversary_config import AdversaryConfig
from policies.learned.generator import RiskFlowGenerator
from policies.learned.guidance_losses import adversarial_loss, map_term, target_rows
from policies.learned.plan_buffer import EncodedView
from policies.learned.sampler import base_velocity
from policies.riskflow.guidance import (
    GuidanceResult,
    GuidanceScene,
    plans_from_velocity,
)
from policies.riskflow.policy import RiskFlowAdversary

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
            per step], or ``gamma`` of plain steps), ``optimizer``, ``normalizer``,
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

    def _guide(
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
