"""The model's input as types: one :class:`Window`, a collated :class:`WindowBatch`.

A :class:`Window` is one scene at one current step, in the scene frame (the ego's pose
at the current step), as numpy arrays (docs/how-to/windows.md); it holds exactly its ``A``
selected agents. :func:`collate_windows` stacks windows into a :class:`WindowBatch` of
torch tensors with a leading batch axis ``B``, padding the agent axis to the largest
``A`` of the batch (padded slots are 0 / False, ``agent_index`` -1, so every mask is
False there). Both are frozen; their arrays are shared (with the dataset, with the
collated batch), so do not modify them in place.

The future fields (``future``, ``future_valid``, ``actions``, ``actions_valid``) are
present in windows cut from recorded scenes (training data) and None in windows of the
live scene (closed-loop planning): all four or none.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

#: Fields whose leading axis is the agent axis A (padded by :func:`collate_windows`).
AGENT_FIELDS = (
    "history",
    "history_valid",
    "future",
    "future_valid",
    "actions",
    "actions_valid",
    "agent_mask",
    "agent_index",
    "length",
    "width",
    "map_crops",
)
#: Fields whose two leading axes are agent axes (A, A).
PAIR_FIELDS = ("pair_features", "pair_mask")
#: Fields present only in windows built from recorded futures (all four or none).
FUTURE_FIELDS = ("future", "future_valid", "actions", "actions_valid")
#: Every field, in the order of the on-disk cache (``policies.learned.data``).
WINDOW_FIELDS = AGENT_FIELDS + PAIR_FIELDS
#: Value of ``agent_index`` in padded slots.
PAD_INDEX = -1


def _check_fields(obj: Any, lead: int) -> None:
    """Agent fields share the ``lead`` leading axes of ``history`` plus A; pair fields
    have (..., A, A); the future fields are all set or all None."""
    future = [getattr(obj, name) is None for name in FUTURE_FIELDS]
    if any(future) and not all(future):
        raise ValueError(f"{type(obj).__name__}: set all of {FUTURE_FIELDS} or none")
    history = obj.history
    if history.ndim != lead + 3:
        raise ValueError(
            f"{type(obj).__name__}.history must have {lead + 3} axes, got {tuple(history.shape)}"
        )
    agents = tuple(history.shape[: lead + 1])
    for name in WINDOW_FIELDS:
        value = getattr(obj, name)
        if value is None:
            continue
        want = agents + (agents[-1],) if name in PAIR_FIELDS else agents
        if tuple(value.shape[: len(want)]) != want:
            raise ValueError(
                f"{type(obj).__name__}.{name} must start with axes {want}, got {tuple(value.shape)}"
            )


class _WindowFields:
    """What :class:`Window` and :class:`WindowBatch` share: the check of their fields
    (``LEAD`` axes before the agent axis), ``has_future``, the fields that are set."""

    LEAD: ClassVar[int]

    def __post_init__(self) -> None:
        _check_fields(self, lead=self.LEAD)

    @property
    def has_future(self) -> bool:
        """Whether the future fields are set (windows of a recorded scene, training batches)."""
        return self.future is not None

    def _set_fields(self) -> Iterator[tuple[str, Any]]:
        for name in WINDOW_FIELDS:
            value = getattr(self, name)
            if value is not None:
                yield name, value


@dataclass(frozen=True, eq=False)
class Window(_WindowFields):
    """One scene at one current step (docs/how-to/windows.md); slot 0 is the ego.

    Frame: positions and headings in the scene frame (the ego's pose at the current
    step, ego at the origin heading along +x); headings wrapped to (-pi, pi]. States at
    unobserved steps are 0 with their valid flag False. ``A`` agents, ``H`` history
    steps (31), ``F`` future steps (52), ``C`` map layers (2), ``S`` crop side (48 px).

    Attributes:
        history: (A, H, 4) float32 states (x [m], y [m], v [m/s], psi [rad]), current
            step last.
        history_valid: (A, H) bool, observed.
        agent_mask: (A,) bool, the agent exists at the current step (all True in a
            window; False only in padded slots of a batch).
        agent_index: (A,) int64 where slot k comes from: the scenario row
            (``window_from_scenario``) or the env slot (``window_from_view``).
        length: (A,) float32 vehicle length [m].
        width: (A,) float32 vehicle width [m].
        map_crops: (A, C, S, S) float32 agent-centred, heading-aligned map crops:
            layer 0 the drivable share [0, 1], layer 1 the SDF [m] clipped to
            +-``WindowConfig.sdf_clip``; columns run along the heading, rows to its left.
        pair_features: (A, A, 8) float32 ``riskflow_env.risk.pairwise_features`` at the
            current step (``[i, j]``: agent j in agent i's frame; [m], [m/s], risk [0, 1]).
        pair_mask: (A, A) bool, pairs that exist and lie within
            ``WindowConfig.interaction_distance`` [m].
        future: (A, F, 4) float32 reference states after the current step (same units
            as ``history``), or None (live scene).
        future_valid: (A, F) bool observed, or None.
        actions: (A, F, 2) float32 (accel [m/s^2], yaw rate [rad/s]) from the current
            state through the future by ``dynamics.inverse``; 0 where invalid; or None.
        actions_valid: (A, F) bool, both end states of the step observed; or None.
    """

    history: np.ndarray
    history_valid: np.ndarray
    agent_mask: np.ndarray
    agent_index: np.ndarray
    length: np.ndarray
    width: np.ndarray
    map_crops: np.ndarray
    pair_features: np.ndarray
    pair_mask: np.ndarray
    future: np.ndarray | None = None
    future_valid: np.ndarray | None = None
    actions: np.ndarray | None = None
    actions_valid: np.ndarray | None = None
    LEAD: ClassVar[int] = 0

    @property
    def num_agents(self) -> int:
        """Agents ``A`` of the window."""
        return int(self.history.shape[0])

    def arrays(self) -> Iterator[tuple[str, np.ndarray]]:
        """``(name, array)`` of every field that is set, in :data:`WINDOW_FIELDS` order."""
        return self._set_fields()


@dataclass(frozen=True, eq=False)
class WindowBatch(_WindowFields):
    """Collated windows: the fields of :class:`Window` as torch tensors with a leading
    batch axis ``B`` and the agent axis padded to ``A = max A_b`` (padded slots: 0,
    False, ``agent_index`` -1). Shapes and units as in :class:`Window`, e.g.
    ``history (B, A, H, 4)`` [m, m, m/s, rad], ``pair_features (B, A, A, 8)``; the
    future fields are None for batches of live-scene windows.

    Attributes:
        history: (B, A, H, 4) states [m, m, m/s, rad], scene frame, current step last.
        history_valid: (B, A, H) bool.
        agent_mask: (B, A) bool, the agent exists (False in padded slots).
        agent_index: (B, A) int64 scenario row or env slot; -1 in padded slots.
        length: (B, A) vehicle length [m].
        width: (B, A) vehicle width [m].
        map_crops: (B, A, C, S, S) drivable share [0, 1] and SDF [m] crops.
        pair_features: (B, A, A, 8) pairwise features at the current step.
        pair_mask: (B, A, A) bool.
        future: (B, A, F, 4) reference future states, or None.
        future_valid: (B, A, F) bool, or None.
        actions: (B, A, F, 2) reference actions (accel [m/s^2], yaw rate [rad/s]), or None.
        actions_valid: (B, A, F) bool, or None.
    """

    history: Tensor
    history_valid: Tensor
    agent_mask: Tensor
    agent_index: Tensor
    length: Tensor
    width: Tensor
    map_crops: Tensor
    pair_features: Tensor
    pair_mask: Tensor
    future: Tensor | None = None
    future_valid: Tensor | None = None
    actions: Tensor | None = None
    actions_valid: Tensor | None = None
    LEAD: ClassVar[int] = 1

    @property
    def batch_size(self) -> int:
        """Scenes ``B``."""
        return int(self.history.shape[0])

    @property
    def num_agents(self) -> int:
        """Agent slots ``A`` (padded)."""
        return int(self.history.shape[1])

    def tensors(self) -> Iterator[tuple[str, Tensor]]:
        """``(name, tensor)`` of every field that is set, in :data:`WINDOW_FIELDS` order."""
        return self._set_fields()

    def map(self, fn: Callable[[Tensor], Tensor]) -> WindowBatch:
        """A batch with ``fn(tensor)`` in place of every tensor that is set."""
        return dataclasses.replace(self, **{name: fn(value) for name, value in self.tensors()})

    def to(self, device: torch.device | str) -> WindowBatch:
        """Every tensor on ``device`` (``Tensor.to``; no copy where already there)."""
        return self.map(lambda tensor: tensor.to(device))

    def scenes(self, start: int, stop: int, num_agents: int | None = None) -> WindowBatch:
        """Scenes ``start:stop`` with the agent axes cut to ``num_agents`` (default all)."""
        agents = slice(0, self.num_agents if num_agents is None else num_agents)
        pick = slice(start, stop)
        return dataclasses.replace(
            self,
            **{
                name: value[(pick, agents, agents) if name in PAIR_FIELDS else (pick, agents)]
                for name, value in self.tensors()
            },
        )

    def require_future(self, what: str) -> None:
        """Raise ValueError naming ``what`` if the future fields are not set."""
        if not self.has_future:
            raise ValueError(
                f"{what} needs a batch with the future fields (docs/how-to/windows.md)"
            )


def collate_windows(windows: Sequence[Window]) -> WindowBatch:
    """Stack windows into a :class:`WindowBatch`, padding the agent axis to the largest A.

    Padded slots are 0 / False (``agent_index``: -1), so every mask is False there.

    Args:
        windows: :class:`Window` objects, all with or all without the future fields.

    Returns:
        The batch (CPU tensors, dtypes of the windows' arrays).
    """
    if not windows:
        raise ValueError("collate_windows needs at least one window")
    if not all(isinstance(window, Window) for window in windows):
        raise TypeError("collate_windows takes Window objects (policies.learned.window_types)")
    if len({window.has_future for window in windows}) != 1:
        raise ValueError("collate_windows: all windows must have the future fields, or none")
    counts = [window.num_agents for window in windows]
    size = max(counts)
    fields = {}
    for name, first in windows[0].arrays():
        tensors = [torch.as_tensor(getattr(window, name)) for window in windows]
        pad_axes = 2 if name in PAIR_FIELDS else 1
        shape = (len(windows),) + (size,) * pad_axes + tuple(first.shape[pad_axes:])
        fill = PAD_INDEX if name == "agent_index" else 0
        out = torch.full(shape, fill, dtype=tensors[0].dtype)
        for row, (tensor, count) in enumerate(zip(tensors, counts, strict=True)):
            out[(row,) + (slice(0, count),) * pad_axes] = tensor
        fields[name] = out
    return WindowBatch(**fields)


__all__ = [
    "AGENT_FIELDS",
    "FUTURE_FIELDS",
    "PAD_INDEX",
    "PAIR_FIELDS",
    "WINDOW_FIELDS",
    "Window",
    "WindowBatch",
    "collate_windows",
]
