"""The env's action input: ``{agent: (accel, yaw_rate)}`` -> one (A, 2) array, validated.

Errors name the agent and what is wrong (unknown or finished agent, missing action,
wrong shape, not real numbers (bools included: a bool array, or a Python/numpy bool in a
list or tuple), NaN/inf, out of bounds when clipping is off). The common case (exactly the
live agents, each a finite (2,) action) takes a vectorised path; anything it does not take
goes agent by agent, so both refuse the same actions.
"""

from __future__ import annotations

import operator
from collections.abc import Mapping, Sequence
from itertools import chain
from typing import Any

import numpy as np

_BOOLS = frozenset((bool, np.bool_))
_DTYPE = operator.attrgetter("dtype")


def _holds_bool(values: list[Any]) -> bool:
    """Whether the actions ``values`` (of an array of int/float dtype, so each an int/float
    or bool array or sequence) may hold a bool, so the checked path must look.

    Arrays: True if a distinct dtype is not a numpy int/float one, or (another library's,
    e.g. torch's) is named bool or complex. Lists and tuples: True if an element's type is
    bool or numpy bool. Both gather the dtypes or types with ``map``, no Python code per
    action.
    """
    try:
        dtypes = set(map(_DTYPE, values))
    except AttributeError:  # lists, tuples: the elements' types
        return not _BOOLS.isdisjoint(map(type, chain.from_iterable(values)))
    return not all(map(_real_dtype, dtypes))


def _real_dtype(dtype: Any) -> bool:
    """A numpy int/float dtype, or another library's dtype not named bool or complex."""
    if isinstance(dtype, np.dtype):
        return dtype.kind in "fiu"
    name = str(dtype)
    return "bool" not in name and "complex" not in name


class ActionInput:
    """Converts action dicts of a fixed agent roster to arrays.

    Args:
        agent_names: the ``possible_agents``, in slot order.
        low: (2,) lower action bounds (accel [m/s^2], yaw rate [rad/s]).
        high: (2,) upper action bounds.
        clip: out-of-bounds actions are allowed (the dynamics clip them); when False
            they raise ValueError.
    """

    def __init__(
        self, agent_names: Sequence[str], low: np.ndarray, high: np.ndarray, clip: bool
    ) -> None:
        self.slot = {name: index for index, name in enumerate(agent_names)}
        self.low, self.high, self.clip = np.asarray(low), np.asarray(high), clip

    def unknown_agent_error(self, agent: Any) -> ValueError:
        """The error for an agent id outside the roster."""
        return ValueError(
            f"unknown agent id {agent!r}; possible agents are 'ego' and "
            f"'agent_1'..'agent_{len(self.slot) - 1}'"
        )

    def to_array(self, actions: Mapping[str, Any], live: Sequence[str]) -> np.ndarray:
        """(A, 2) float64 actions of the ``live`` agents (zeros elsewhere), validated.

        Args:
            actions: ``{agent: (accel [m/s^2], yaw_rate [rad/s])}`` for exactly ``live``.
            live: the live agents.
        """
        if isinstance(actions, Mapping) and len(actions) == len(live):
            try:  # fast path: exactly the live agents, each a finite (2,) action
                slots = [self.slot[agent] for agent in actions]
                raw = list(actions.values())
                values = np.array(raw)
                if values.dtype.kind not in "fiu" or _holds_bool(raw):  # bool, str...: checked
                    raise TypeError(values.dtype)
                values = values.astype(np.float64, copy=False)
            except (KeyError, ValueError, TypeError, RuntimeError):
                slots, values = None, None
            if (
                values is not None
                and values.shape == (len(slots), 2)
                and actions.keys() == set(live)
                and np.isfinite(values).all()
            ):
                array = np.zeros((len(self.slot), 2))
                array[slots] = values
                if self.clip or not self._out_of_bounds(array).any():
                    return array
        return self._checked(actions, live)

    def _out_of_bounds(self, array: np.ndarray) -> np.ndarray:
        return np.any((array < self.low) | (array > self.high), axis=-1)

    def _checked(self, actions: Mapping[str, Any], live: Sequence[str]) -> np.ndarray:
        """Agent by agent, with an error naming the agent and what is wrong."""
        if not isinstance(actions, Mapping):
            raise TypeError(
                f"actions must be a dict {{agent: action}}, got {type(actions).__name__}"
            )
        for agent in actions:
            if agent not in self.slot:
                raise self.unknown_agent_error(agent)
        not_live = sorted(set(actions) - set(live))
        if not_live:
            raise ValueError(f"actions given for agents that are not live: {not_live}")
        missing = [agent for agent in live if agent not in actions]
        if missing:
            raise ValueError(f"actions missing for live agents: {missing}")
        array = np.zeros((len(self.slot), 2))
        for agent, action in actions.items():
            array[self.slot[agent]] = self.check(agent, action, bounds=False)
        if not np.all(np.isfinite(array)):
            bad = [agent for agent in actions if not np.all(np.isfinite(array[self.slot[agent]]))]
            raise ValueError(f"actions must be finite; got NaN or inf for {_names(bad)}")
        if not self.clip:
            outside = self._out_of_bounds(array)
            if np.any(outside):
                raise self._bounds_error([agent for agent in actions if outside[self.slot[agent]]])
        return array

    def check(self, agent: str, action: Any, bounds: bool = True) -> np.ndarray:
        """One agent's action as a (2,) float64 array, or a ValueError naming the agent: not
        real numbers (a bool array, or a list/tuple holding a Python/numpy bool, included),
        not of shape (2,), and (``bounds``) NaN/inf or out of bounds when clipping is off.
        The AEC view checks each action with it as it is given."""
        try:
            raw = np.asarray(action)
        except (ValueError, TypeError, RuntimeError) as error:
            raise ValueError(
                f"actions[{agent!r}] must be a real (accel, yaw_rate) pair: {error}"
            ) from None
        if raw.dtype.kind not in "fiu":
            raise ValueError(
                f"actions[{agent!r}] must hold real numbers, got dtype {raw.dtype} ({action!r:.60})"
            )
        if isinstance(action, (list, tuple)) and _holds_bool([action]):  # e.g. (True, 0.5)
            raise ValueError(
                f"actions[{agent!r}] must hold real numbers, got a bool in {action!r:.60}"
            )
        value = raw.astype(np.float64)
        if value.shape != (2,):
            raise ValueError(
                f"actions[{agent!r}] must have shape (2,) = (accel, yaw_rate), "
                f"got shape {value.shape}"
            )
        if bounds and not np.all(np.isfinite(value)):
            raise ValueError(f"actions must be finite; got NaN or inf for {[agent]}")
        if bounds and not self.clip and self._out_of_bounds(value):
            raise self._bounds_error([agent])
        return value

    def _bounds_error(self, agents: list[str]) -> ValueError:
        return ValueError(
            f"actions out of bounds for {_names(agents)}: accel must be in "
            f"[{self.low[0]}, {self.high[0]}] m/s^2 and yaw rate in "
            f"[{self.low[1]}, {self.high[1]}] rad/s "
            "(EnvConfig(clip_actions=True) clips instead)"
        )


def _names(agents: list[str], shown: int = 5) -> str:
    """The first ``shown`` agent names of ``agents``, and how many more."""
    more = len(agents) - shown
    return str(agents[:shown]) + (f" and {more} more" if more > 0 else "")
