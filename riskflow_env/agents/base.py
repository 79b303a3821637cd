"""What scene policies share: which slots a policy controls, and its actions as a dict."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from riskflow_env.view import ScenePolicy, SceneView

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


def check_policy(policy: object) -> ScenePolicy:
    """``policy`` itself if it is a :class:`ScenePolicy`; TypeError naming it otherwise."""
    if not isinstance(policy, ScenePolicy):
        raise TypeError(
            "policy must be a ScenePolicy (with reset(view) and act(view)), "
            f"got {type(policy).__name__}"
        )
    return policy


def restart_policy(policy: ScenePolicy, view: SceneView, seed: int | None) -> None:
    """Start a policy's episode: with a ``seed``, a policy that has ``reseed(seed)`` (the
    learned adversaries) is reseeded first, so a seeded env reset repeats the episode bit
    for bit, the policy's noise included; then ``policy.reset(view)``."""
    reseed = getattr(policy, "reseed", None)
    if seed is not None and callable(reseed):
        reseed(seed)
    policy.reset(view)


def policy_actions(
    policy: ScenePolicy, view: SceneView, driven: Sequence[str], role: str
) -> dict[str, np.ndarray]:
    """``policy.act(view)``, checked: actions for exactly the live agents ``driven``.

    Args:
        policy: the scene policy.
        view: the scene.
        driven: the live agents the policy must drive (none: the policy is not asked).
        role: who they are, for the error message (e.g. ``"other than the ego"``).
    """
    proposed = policy.act(view) if driven else {}
    unexpected = sorted(set(proposed) - set(driven))
    missing = [agent for agent in driven if agent not in proposed]
    if unexpected or missing:
        raise ValueError(
            f"policy {type(policy).__name__} must act for exactly the live agents {role}; "
            f"missing {missing}, unexpected {unexpected}"
        )
    return proposed
