"""The render overlay of a plan-buffer policy: this cycle's plans on the video frames.

:class:`PlanOverlay` is a mixin of :class:`~policies.learned.plan_buffer.PlanBufferPolicy`.
It reads what the last planning cycle stored (``plans`` (A, T, 4) world-frame states,
``plan_mask`` (A,), ``controllable`` (A,) = ``A_c``, the slot names ``_names``) and pushes
two overlays to a renderer (``SceneRenderer.set_overlay``): the plans of the unguided
vehicles, and the guided plans of ``A_c``, haloed.
"""

from __future__ import annotations

import numpy as np

BASE_COLOR = (70, 200, 235)  # overlay of the unguided plans
GUIDED_COLOR = (200, 80, 235)  # overlay of the guided (A_c) plans (purple: red marks collisions)


class PlanOverlay:
    """Overlays of the stored plans (module docstring); ``overlay_prefix`` names them."""

    overlay_prefix = "riskflow"
    plans: np.ndarray | None
    plan_mask: np.ndarray
    controllable: np.ndarray
    _names: tuple[str, ...]

    @property
    def controllable_names(self) -> tuple[str, ...]:
        """Names of the agents in ``A_c`` this cycle (set by the last ``act``)."""
        return tuple(self._names[i] for i in np.flatnonzero(self.controllable))

    def draw(self, renderer) -> None:
        """Push this cycle's plans to a renderer (``SceneRenderer.set_overlay``): base plans
        of the unguided vehicles, guided plans of ``A_c`` (highlighted)."""
        if self.plans is None:
            return
        others = self.plan_mask & ~self.controllable
        prefix = self.overlay_prefix
        renderer.set_overlay(
            f"{prefix}_base", self.plans[..., :2], others, BASE_COLOR, label="base plans"
        )
        renderer.set_overlay(
            f"{prefix}_guided",
            self.plans[..., :2],
            self.controllable,
            GUIDED_COLOR,
            highlight=tuple(int(i) for i in np.flatnonzero(self.controllable)),
            label="guided plans (A_c, haloed)",
        )


__all__ = ["BASE_COLOR", "GUIDED_COLOR", "PlanOverlay"]
