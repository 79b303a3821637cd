"""What scene policies share: which slots a policy controls, and its actions as a dict."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from riskflow_env.view import SceneView

CONTROLLED_GROUPS = ("others", "all")


def controlled_mask(view: SceneView, controlled: str | Sequence[str]) -> np.ndarray:
    """(A,) bool: the live slots a policy with ``controlled`` drives.

    Args:
        view: the scene.
        controlled: ``"others"`` (every vehicle but the ego), ``"all"``, or agent names.
    """
    if isinstance(controlled, str):
        if controlled not in CONTROLLED_GROUPS:
            raise ValueError(
                f"controlled must be one of {CONTROLLED_GROUPS} or a sequence of agent names, "
                f"got {controlled!r}"
            )
        mask = np.ones(view.num_agents, dtype=bool)
        if controlled == "others":
            mask[0] = False
    else:
        mask = np.zeros(view.num_agents, dtype=bool)
        for name in controlled:
            mask[view.slot(name)] = True
    return mask & view.active


def actions_dict(view: SceneView, mask: np.ndarray, actions: np.ndarray) -> dict[str, np.ndarray]:
    """``{name: actions[slot]}`` for the slots in ``mask``; actions (A, 2)."""
    return {view.agent_names[i]: actions[i] for i in np.flatnonzero(mask)}
