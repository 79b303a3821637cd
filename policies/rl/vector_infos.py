"""The ego's step infos of a batch of scenes, as Gymnasium vector envs report infos.

One step of ``EgoEnv`` reports, for the ego, ``reward_terms`` (term -> weighted value),
``collided``, ``collided_with`` (the names of the vehicles it overlaps),
``offroad_fraction`` and ``sdf_depth`` (:meth:`RiskFlowParallelEnv._agent_dicts`).
:func:`step_infos` gives the same values for every scene of a batched
:class:`~riskflow_env.simulator.Transition`, in the layout of
``gymnasium.vector.VectorEnv._add_info``: per key an (N,) array and a boolean mask
``_key`` (nested for ``reward_terms``), read from the transition's arrays at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from riskflow_env.simulator import Transition


def collision_partners(collisions: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """(N,) object array: per scene, the list of the names of the vehicles slot 0 overlaps.

    Args:
        collisions: (N, A) bool, the ego's row of each scene's collision matrix.
        names: the A slot names.
    """
    partners = np.empty(len(collisions), dtype=object)
    partners[:] = [[] for _ in range(len(collisions))]
    for scene, slot in np.argwhere(collisions).tolist():  # only the colliding pairs
        partners[scene].append(names[slot])
    return partners


def _with_masks(values: dict[str, Any], count: int) -> dict[str, Any]:
    """``values`` with a True mask ``_key`` beside every key (recursively)."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        out[key] = _with_masks(value, count) if isinstance(value, dict) else value
        out[f"_{key}"] = np.ones(count, dtype=bool)
    return out


def _merge(rows: np.ndarray, new: dict[str, Any], old: dict[str, Any]) -> dict[str, Any]:
    """``new`` in the scenes ``rows``, ``old`` elsewhere (recursively; masks kept)."""
    merged: dict[str, Any] = {}
    for key, value in new.items():
        if key.startswith("_"):
            merged[key] = value
        elif isinstance(value, dict):
            merged[key] = _merge(rows, value, old[key])
        else:
            merged[key] = np.where(rows, value, old[key])
    return merged


def step_infos(
    transition: Transition,
    names: Sequence[str],
    rows: np.ndarray,
    previous: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The ego's infos of every scene of ``transition`` (module docstring).

    Args:
        transition: a step of N scenes (arrays (N, A, ...)).
        names: the A slot names.
        rows: (N,) bool, the scenes whose infos this step gives; the others keep
            ``previous`` (scenes already done within an action repeat).
        previous: the infos of the step before (None or empty: none).
    """
    events = transition.events
    count = len(rows)
    values = {
        "reward_terms": {
            name: np.array(term[:, 0], dtype=np.float64)
            for name, term in transition.reward_terms.items()
        },
        "collided": np.array(events.collided[:, 0], dtype=bool),
        "collided_with": collision_partners(np.asarray(events.collisions[:, 0]), names),
        "offroad_fraction": np.array(events.offroad_fraction[:, 0], dtype=np.float64),
        "sdf_depth": np.array(events.sdf_depth[:, 0], dtype=np.float64),
    }
    infos = _with_masks(values, count)
    if previous:
        infos = _merge(np.asarray(rows, dtype=bool), infos, previous)
    return infos


def scene_info(infos: dict[str, Any], index: int) -> dict[str, Any]:
    """Scene ``index``'s info dict out of vector infos (the keys its masks select;
    ``final_obs`` / ``final_info`` left out): what a single env's ``step`` returns."""
    out: dict[str, Any] = {}
    for key, value in infos.items():
        if key.startswith("_") or key in ("final_obs", "final_info"):
            continue
        mask = infos.get(f"_{key}")
        if mask is not None and not mask[index]:
            continue
        out[key] = scene_info(value, index) if isinstance(value, dict) else value[index]
    return out


__all__ = ["collision_partners", "scene_info", "step_infos"]
