"""``PlanSet``: what the stages of one planning cycle hand each other.

One value for the B scenes planned together: their views and planner states (as the
cycle found them), what the window stage observed, and the plans of every vehicle of
every scene, torch tensors in each scene's ego frame with a leading scene axis
``(B, A, ...)`` (agents padded to the largest scene and masked). The frame, the dtype and
numpy / torch change at the edges only: the ``encode`` stage reads the views into the
ego frame, the ``emit`` stage writes world-frame numpy plans into new planner states.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from policies.learned.encoder import SceneContext
from policies.learned.ranking import Ranking
from policies.learned.window_types import Window, WindowBatch
from policies.pipeline.state import PlannerState
from riskflow_env.maps import DrivableMap, MapStack
from riskflow_env.view import SceneView


@dataclass(frozen=True)
class EncodedViews:
    """What the ``encode`` stage observed of B scenes.

    Attributes:
        windows: the B :class:`Window` objects (``docs/how-to/windows.md``; ego frame, ego in
            slot 0; no future fields).
        slots: B arrays (A_b,): env slot of each window row of each scene.
        batch: the collated windows (agents padded to A = max A_b) on the policy's device.
        scene: the encoder's :class:`SceneContext` of ``batch`` (no gradients), (B, A, ...).
        frames: (B, 3) world pose of each scene frame: its ego's (x [m], y [m], psi [rad]).
        clock: ``time.perf_counter()`` after the encoder (start of the next phase).
    """

    windows: list[Window]
    slots: list[np.ndarray]
    batch: WindowBatch
    scene: SceneContext
    frames: np.ndarray
    clock: float

    @property
    def counts(self) -> list[int]:
        """Agents A_b of each scene's window."""
        return [len(slots) for slots in self.slots]

    def frame_tensor(self) -> torch.Tensor:
        """(B, 3) ``frames`` as a tensor of the context's dtype and device (for ``L_map``)."""
        state = self.scene.state
        return torch.as_tensor(self.frames, dtype=state.dtype, device=state.device)


@dataclass(frozen=True)
class PlanSet:
    """The plans of one cycle of B scenes (module docstring); a stage returns a new one.

    Attributes:
        views: the B scenes now.
        states: their planner states before this cycle.
        drivable_map: the scenes' maps for one lookup (one shared map or a ``MapStack``).
        observed: windows, collated batch and encoder context (``encode``).
        controllable: (B, A) bool ``A_c`` (``rank``); None: no vehicle is guided.
        rankings: per scene, how ``A_c`` was chosen (``rank``).
        eps: (B, A, T, 2) the noise of the base plans (``generate``).
        u: (B, A, T, 2) the base residual ``u0`` in normalised action space (``generate``,
            then ``stitch`` and ``avoid``).
        gain: (B, A, T, 1) the share of an avoidance correction that reaches the plan
            (``stitch``), or None (all of it).
        base_actions: (B, A, T, 2) [m/s^2, rad/s] the unguided plans (``decode``).
        base_trajectories: (B, A, T, 4) their states (x, y [m], v [m/s], psi [rad]).
        actions: (B, A, T, 2) the plans to run (``guide``; None: the unguided ones).
        trajectories: (B, A, T, 4) their states.
        losses: (N, B, 2) ``L_adv``, ``L_map`` per guidance step (``guide``).
        noise: per scene, the noise to keep (None: ``eps``'s rows).
        extras: per scene, a method's own outputs to keep (``PlannerState.extras``).
        new_states: the planner states after this cycle (``emit``).
    """

    views: Sequence[SceneView]
    states: Sequence[PlannerState]
    drivable_map: DrivableMap | MapStack
    observed: EncodedViews | None = None
    controllable: Tensor | None = None
    rankings: Sequence[Ranking | None] = ()
    eps: Tensor | None = None
    u: Tensor | None = None
    gain: Tensor | None = None
    base_actions: Tensor | None = None
    base_trajectories: Tensor | None = None
    actions: Tensor | None = None
    trajectories: Tensor | None = None
    losses: Tensor | None = None
    noise: Sequence[Tensor] | None = None
    extras: Sequence[dict[str, Any]] = ()
    new_states: Sequence[PlannerState] = field(default=())

    def replace(self, **changes: Any) -> PlanSet:
        """A copy with ``changes`` (what a stage returns)."""
        return dataclasses.replace(self, **changes)


__all__ = ["EncodedViews", "PlanSet"]
