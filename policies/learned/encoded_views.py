"""What one planning call observes of its scenes: windows, the collated batch, the context.

:func:`encode_views` (the ``encode`` stage of :mod:`policies.pipeline.stages`) cuts a
window from each scene's view, collates them (agents padded to the largest scene) and runs
the model's encoder once; :class:`EncodedViews` holds the result for B scenes, and
:meth:`EncodedViews.view` cuts scene ``b`` out as :class:`EncodedView`, without padding.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from policies.learned.encoder import SceneContext
from policies.learned.window_types import Window, WindowBatch, collate_windows
from policies.learned.windows import WindowConfig, window_from_view
from riskflow_env.view import SceneView


@dataclass(frozen=True)
class EncodedView:
    """One cycle's observation of the scene (:meth:`EncodedViews.view`).

    Attributes:
        window: the :class:`Window` (``docs/how-to/windows.md``; ego frame, ego in slot 0; no
            future fields).
        slots: (A_w,) env slot of each window row.
        batch: the collated window (batch of one, no padding) on the policy's device.
        scene: the encoder's :class:`SceneContext` of ``batch`` (no gradients).
        frame: (3,) world pose of the scene frame: the ego's (x [m], y [m], psi [rad]).
        clock: ``time.perf_counter()`` after the encoder (start of the next phase).
    """

    window: Window
    slots: np.ndarray
    batch: WindowBatch
    scene: SceneContext
    frame: np.ndarray
    clock: float

    def frame_tensor(self) -> torch.Tensor:
        """``frame`` as a tensor of the context's dtype and device (for ``L_map``)."""
        state = self.scene.state
        return torch.as_tensor(self.frame, dtype=state.dtype, device=state.device)


@dataclass(frozen=True)
class EncodedViews:
    """One planning call's observation of B scenes (:func:`encode_views`).

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

    def view(self, index: int) -> EncodedView:
        """Scene ``index`` alone (its own A_b agents: no padding), as one-scene planning
        sees it."""
        count, pick = self.counts[index], slice(index, index + 1)
        batch = self.batch.scenes(index, index + 1, count)
        scene = self.scene
        agents, pairs = (pick, slice(0, count)), (pick, slice(0, count), slice(0, count))
        context = SceneContext(
            context=scene.context[agents],
            edges=scene.edges[pairs],
            social_mask=scene.social_mask[pairs],
            agent_mask=scene.agent_mask[agents],
            state=scene.state[agents],
        )
        window, slots = self.windows[index], self.slots[index]
        return EncodedView(window, slots, batch, context, self.frames[index], self.clock)


def encode_views(
    views: Sequence[SceneView],
    window_config: WindowConfig,
    device: torch.device,
    encode: Callable[[WindowBatch], SceneContext],
    tick: Callable[[str, float], float],
) -> EncodedViews:
    """Windows, collate (agents padded), one encoder pass. The windows are cut scene by
    scene (a loop over scenes: ``window_from_view`` is per scene, numpy).

    Args:
        views: the B scenes now.
        window_config: the window options.
        device: where the batch goes.
        encode: the model's encoder, ``batch -> SceneContext`` (run without gradients).
        tick: the phase clock, ``tick(phase, start) -> now`` (records the phases
            ``"window"`` and ``"encoder"``).
    """
    start = time.perf_counter()
    windows = [window_from_view(view, window_config) for view in views]
    batch = collate_windows(windows).to(device)
    clock = tick("window", start)
    with torch.no_grad():
        scene = encode(batch)
    clock = tick("encoder", clock)
    frames = np.array([[v.current[0, 0], v.current[0, 1], v.current[0, 3]] for v in views])
    slots = [w.agent_index for w in windows]
    return EncodedViews(windows, slots, batch, scene, frames, clock)


__all__ = ["EncodedView", "EncodedViews", "encode_views"]
