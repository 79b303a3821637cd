"""What a RiskFlow planning cycle does to the base plans before guidance, as methods of
:class:`~policies.riskflow.policy.RiskFlowAdversary` (and so of STRIVE-style and the
unguided generator): blending them into the executed plans and the avoidance steps."""

from __future__ import annotations

from collections.abc import Sequence
from types import SimpleNamespace

import numpy as np
import torch

from policies.learned.encoded_views import EncodedViews
from policies.learned.guidance_losses import map_term, target_rows
from policies.learned.plan_avoidance import avoid_overlaps, guided_pairs
from policies.learned.plan_buffer import PlanBufferPolicy
from policies.learned.plan_overlap import OVERLAP_HORIZON
from policies.learned.plan_stitching import CORRECTION_STITCH_STEPS, blend_share
from riskflow_env.view import SceneView


class BasePlanSteps:
    """The base-plan steps of a planning cycle (module docstring); the host class has the
    generator's ``normalizer``, ``dynamics``, ``device``, ``guidance`` (its objective),
    ``avoid_steps``, ``avoid_step_size`` and ``_map_of``."""

    def _blend_first(
        self,
        scenes: Sequence[PlanBufferPolicy],
        views: Sequence[SceneView],
        slots: Sequence[np.ndarray],
        eps: torch.Tensor,
        u0: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The base residual ``u0`` (B, A, T, 2) of plans whose first actions are blended
        into each scene's executed plans (blending first,
        :mod:`policies.learned.plan_stitching`), and the gain (B, A, T, 1) of the
        avoidance steps' corrections: blended over ``CORRECTION_STITCH_STEPS``."""
        old, share = torch.zeros_like(u0), torch.zeros_like(u0[..., :1])
        for index, (policy, view) in enumerate(zip(scenes, views, strict=True)):
            blend = policy._continuation(view, slots[index], u0.shape[2])
            if blend is not None:
                previous, weight = (torch.as_tensor(x, dtype=u0.dtype) for x in blend)
                rows, steps = slice(0, len(slots[index])), weight.shape[1]
                old[index, rows, :steps] = previous.to(u0.device)
                share[index, rows, :steps, 0] = weight.to(u0.device)
        actions = self.normalizer.denormalize(eps + u0)
        blended = self.normalizer.normalize(share * old + (1 - share) * actions) - eps
        steps = min(CORRECTION_STITCH_STEPS, share.shape[2])
        gain = torch.ones_like(share)
        gain[:, :, :steps] -= torch.where(
            share[:, :, :steps] > 0, share.new_tensor(blend_share(steps))[:, None], 0.0
        )
        return blended, gain

    def _map_term_of_rows(
        self, observed: EncodedViews, views: Sequence[SceneView], rows: torch.Tensor | None = None
    ):
        """The guidance's map term over the first ``OVERLAP_HORIZON`` steps of the
        ``rows`` of the ``B * A`` agent rows (scene after scene; None: every row), or None
        without ``L_map``; the avoidance steps' off-road score."""
        batch, num_agents = observed.batch, observed.scene.agent_mask.shape[1]
        if rows is None:
            rows = torch.arange(observed.scene.agent_mask.numel(), device=self.device)
        flat = SimpleNamespace(
            length=batch.length.flatten(), width=batch.width.flatten(),
            drivable_map=self._map_of(views), frame=observed.frame_tensor(),
        )  # fmt: skip
        return map_term(flat, rows, OVERLAP_HORIZON, self.guidance, rows // num_agents)

    def _avoid(
        self,
        observed: EncodedViews,
        views: Sequence[SceneView],
        eps: torch.Tensor,
        u0: torch.Tensor,
        gain: torch.Tensor | None = None,
        controllable: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Avoidance steps on the base plans of every scene
        (:func:`~policies.learned.plan_avoidance.avoid_overlaps`; ``gain`` the share of
        each step's correction that is kept, blending first): ``(u0, actions,
        trajectories)`` after them. The pairs of a vehicle of ``A_c`` (``controllable``,
        (B, A) bool) and one of its targets are left to guidance, when it pulls them
        together (``lambda_adv > 0``)."""
        scene, batch = observed.scene, observed.batch
        exempt = None
        if controllable is not None and self.guidance.lambda_adv > 0 and bool(controllable.any()):
            targets = target_rows(scene.agent_mask, controllable, 0, self.guidance.target)
            exempt = guided_pairs(controllable, targets)
        return avoid_overlaps(
            eps, u0, scene.state, batch.length, batch.width, scene.agent_mask,
            lambda rows: self._map_term_of_rows(observed, views, rows),
            self.normalizer, self.dynamics, steps=self.avoid_steps,
            step_size=self.avoid_step_size, gain=gain, exempt=exempt,
        )  # fmt: skip


__all__ = ["BasePlanSteps"]
