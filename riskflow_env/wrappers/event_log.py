"""Event log: every collision and off-road episode, once at its onset and once at its end.

:class:`EventLogWrapper` wraps a ``riskflow_v0`` ``ParallelEnv``; after every ``reset`` and
``step`` it reads the env's :attr:`~riskflow_env.env.RiskFlowParallelEnv.last_events`
(collisions and off-road flags the env already computed) and its read-only ``view()``,
and turns the per-step flags into events. Events are kept in memory (``wrapper.events``,
a list of JSON-ready dicts) and, with ``path=``, appended to a JSON Lines file, one
object per line, flushed as soon as it is written: a run killed at any point leaves
every event detected before the kill on disk.

=====================  ==================================================================
``event``              fields (besides ``event``, ``episode``, ``step``, ``time`` [s])
=====================  ==================================================================
``collision_start``    ``agents`` [a, b] (slot order, the ego first), ``ego_involved``,
                       ``positions`` [[x, y], [x, y]] [m], ``relative_speed`` [m/s]
                       (norm of the velocity difference), ``contact_point`` [x, y] [m],
                       ``contact`` [kind of a, kind of b], each "front", "rear" or "side"
``collision_end``      ``agents``, ``ego_involved``, ``start_step``, ``duration`` [s],
                       ``cause`` ("separated", or why the episode ended: "done",
                       "reset", "close", "exit", "exception")
``offroad_start``      ``agent``, ``ego_involved``, ``position`` [x, y] [m],
                       ``offroad_fraction`` (share of the 9 footprint samples outside the
                       drivable area), ``sdf_depth`` [m] (largest SDF over the footprint)
``offroad_end``        ``agent``, ``ego_involved``, ``start_step``, ``duration`` [s],
                       ``max_offroad_fraction``, ``max_sdf_depth`` [m], ``cause``
``episode_summary``    ``scenario``, ``steps``, ``end_reason``, ``collisions``,
                       ``ego_collisions``, ``offroad_events``, ``ego_offroad_events``,
                       ``ego_collided``, ``time_to_first_collision`` [s] and
                       ``time_to_first_ego_collision`` [s] (null when none)
=====================  ==================================================================

``duration`` counts the steps in contact (off the road) times ``dt``. The contact point
and kinds are :mod:`~riskflow_env.wrappers.event_contact`'s; the file is read back, and
resumed, by :mod:`~riskflow_env.wrappers.event_log_file` (``read_event_log`` is
re-exported here).

The file is flushed after every event, at episode end, at ``close()``, when an exception
leaves a ``with`` block, and (``weakref.finalize``) at interpreter exit or when the
wrapper is garbage collected without being closed.
"""

from __future__ import annotations

import json
import os
import weakref
from typing import Any

import numpy as np
from pettingzoo.utils import BaseParallelWrapper

from riskflow_env.dynamics import SPEED, YAW
from riskflow_env.env import RiskFlowParallelEnv
from riskflow_env.events import contact_pairs
from riskflow_env.folder_lock import file_path, make_output_file
from riskflow_env.wrappers.event_contact import contact_kind, contact_point
from riskflow_env.wrappers.event_log_file import (
    check_event_log,
    drop_torn_tail,
    last_episode,
    read_event_log,
)


def _round(value: Any) -> Any:
    """Plain-Python, JSON-ready copy of floats / arrays, rounded to 1e-4."""
    return (np.round(np.asarray(value, dtype=np.float64), 4) + 0.0).tolist()  # no -0.0


class EventRecorder:
    """Turns per-step event flags into onset / ending events; the wrapper's engine.

    Usable without the wrapper: call :meth:`begin` after a reset, :meth:`observe` after
    every step, :meth:`finish` at episode end and :meth:`close` at the end of the run.

    Args:
        path: JSON Lines file to write, or None to keep the events in memory only.
        append: append to an existing file (a torn last line of a killed run is dropped;
            episode numbers continue after the file's last one).
        overwrite: replace an existing non-empty file. Without ``append`` or
            ``overwrite``, a non-empty file raises FileExistsError (a killed run's log
            is never destroyed silently).
    """

    def __init__(
        self,
        path: str | os.PathLike | None = None,
        append: bool = False,
        overwrite: bool = False,
    ) -> None:
        for name, flag in (("append", append), ("overwrite", overwrite)):
            if not isinstance(flag, bool):
                raise ValueError(f"{name} must be True or False, got {flag!r}")
        self.path = None if path is None else file_path(path)
        self.events: list[dict[str, Any]] = []
        self._file = None
        self._episode = -1  # the episode being recorded; begin() moves to the next
        if append and overwrite:
            raise ValueError("EventRecorder: append and overwrite exclude each other")
        if self.path is not None:
            make_output_file(self.path, "path", in_place=True)  # appends or writes in place
            exists = self.path.is_file() and self.path.stat().st_size > 0
            if exists and not (append or overwrite):
                raise FileExistsError(
                    f"event log {self.path} already holds events (a previous or killed run?); "
                    "pass append=True to continue it or overwrite=True to replace it"
                )
            if exists and append:
                check_event_log(self.path)
                drop_torn_tail(self.path)
                self._episode = last_episode(self.path)  # a resumed log keeps counting
            mode = "a" if append else "w"
            self._file = open(self.path, mode, buffering=1, encoding="utf-8")
        self._open = False

    def begin(self, scenario: str = "") -> None:
        """Start a new episode (finishing an unfinished one with reason "reset")."""
        if self._open:
            self.finish("reset")
        self._episode += 1
        self._open = True
        self._scenario = scenario
        self._step, self._dt, self._names = 0, 0.1, ()
        self._collisions: dict[tuple[int, int], dict[str, Any]] = {}
        self._offroad: dict[int, dict[str, Any]] = {}
        self._counts = dict.fromkeys(
            ("collisions", "ego_collisions", "offroad_events", "ego_offroad_events"), 0
        )
        self._first: dict[str, float | None] = {"any": None, "ego": None}

    def observe(self, view: Any, events: Any) -> None:
        """Record the onsets and endings between the previous step and this one.

        Args:
            view: the env's :class:`~riskflow_env.view.SceneView` at this step.
            events: the env's :class:`~riskflow_env.events.FrameEvents` at this step.
        """
        if not self._open:
            self.begin(view.scenario.name)
        self._step, self._dt, self._names = view.step, view.dt, view.agent_names
        names = self._names
        pairs = contact_pairs(events.collisions)
        for pair in sorted(set(self._collisions) - pairs):
            self._end_collision(pair, "separated", self._step)
        for i, j in sorted(pairs - set(self._collisions)):
            self._start_collision(view, i, j)
        offroad = set(np.flatnonzero(events.offroad).tolist())
        for slot in sorted(set(self._offroad) - offroad):
            self._end_offroad(slot, "separated", self._step)
        for slot in sorted(offroad):
            fraction, depth = float(events.offroad_fraction[slot]), float(events.sdf_depth[slot])
            if slot not in self._offroad:
                self._counts["offroad_events"] += 1
                self._counts["ego_offroad_events"] += slot == 0
                self._offroad[slot] = {"start": self._step, "fraction": 0.0, "depth": -np.inf}
                self._emit(
                    "offroad_start",
                    agent=names[slot],
                    ego_involved=slot == 0,
                    position=_round(view.current[slot, :2]),
                    offroad_fraction=_round(fraction),
                    sdf_depth=_round(depth),
                )
            entry = self._offroad[slot]
            entry["fraction"] = max(entry["fraction"], fraction)
            entry["depth"] = max(entry["depth"], depth)

    def finish(self, reason: str = "done") -> dict[str, Any] | None:
        """End the episode: close open events with cause ``reason``, write the summary."""
        if not self._open:
            return None
        last = self._step + 1  # an event still open was observed through the last step
        for pair in sorted(self._collisions):
            self._end_collision(pair, reason, last)
        for slot in sorted(self._offroad):
            self._end_offroad(slot, reason, last)
        self._open = False
        return self._emit(
            "episode_summary",
            scenario=self._scenario,
            steps=self._step,
            end_reason=reason,
            **self._counts,
            ego_collided=self._counts["ego_collisions"] > 0,
            time_to_first_collision=self._first["any"],
            time_to_first_ego_collision=self._first["ego"],
        )

    def close(self, reason: str = "close") -> None:
        """Finish an unfinished episode with ``reason``, flush and close the file."""
        self.finish(reason)
        if self._file is not None and not self._file.closed:
            self._file.flush()
            self._file.close()

    # ---------------------------------------------------------------- internals
    def _emit(self, event: str, **fields: Any) -> dict[str, Any]:
        step = fields.pop("at_step", self._step)
        row = {"event": event, "episode": self._episode, "step": step}
        row |= {"time": _round(step * self._dt), **fields}
        self.events.append(row)
        if self._file is not None and not self._file.closed:
            self._file.write(json.dumps(row) + "\n")
            self._file.flush()
        return row

    def _start_collision(self, view: Any, i: int, j: int) -> None:
        current, slots = view.current, [i, j]
        xy, yaw = current[slots, :2], current[slots, YAW]
        length, width = view.length[slots], view.width[slots]
        point = contact_point(xy, yaw, length, width)
        velocity = current[slots, SPEED, None] * np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
        ego = i == 0
        time = _round(self._step * self._dt)
        self._counts["collisions"] += 1
        self._counts["ego_collisions"] += ego
        if self._first["any"] is None:
            self._first["any"] = time
        if ego and self._first["ego"] is None:
            self._first["ego"] = time
        self._collisions[(i, j)] = {"start": self._step}
        self._emit(
            "collision_start",
            agents=[view.agent_names[i], view.agent_names[j]],
            ego_involved=ego,
            positions=_round(xy),
            relative_speed=_round(np.linalg.norm(velocity[0] - velocity[1])),
            contact_point=_round(point),
            contact=[contact_kind(point, xy[k], yaw[k], length[k], width[k]) for k in (0, 1)],
        )

    def _end_collision(self, pair: tuple[int, int], cause: str, end_step: int) -> None:
        start = self._collisions.pop(pair)["start"]
        self._emit(
            "collision_end",
            at_step=min(end_step, self._step),
            agents=[self._names[pair[0]], self._names[pair[1]]],
            ego_involved=pair[0] == 0,
            start_step=start,
            duration=_round((end_step - start) * self._dt),
            cause=cause,
        )

    def _end_offroad(self, slot: int, cause: str, end_step: int) -> None:
        entry = self._offroad.pop(slot)
        self._emit(
            "offroad_end",
            at_step=min(end_step, self._step),
            agent=self._names[slot],
            ego_involved=slot == 0,
            start_step=entry["start"],
            duration=_round((end_step - entry["start"]) * self._dt),
            max_offroad_fraction=_round(entry["fraction"]),
            max_sdf_depth=_round(entry["depth"]),
            cause=cause,
        )


def require_riskflow_env(env: Any, owner: str) -> None:
    """TypeError naming ``owner`` unless ``env`` is a ``riskflow_v0`` env or wraps one."""
    if not isinstance(getattr(env, "unwrapped", None), RiskFlowParallelEnv):
        raise TypeError(
            f"{owner}: env must be a riskflow_v0 env (riskflow_env.parallel_env()) or a "
            f"wrapper of one, got {type(env).__name__}"
        )


class EventLogWrapper(BaseParallelWrapper):
    """Records collision and off-road events of a ``riskflow_v0`` env (see module doc).

    Args:
        env: the env, or a wrapper of it (its ``unwrapped`` must be a RiskFlow env).
        path: JSON Lines file to write; None keeps events in memory only.
        append: append to ``path`` (e.g. when resuming a killed run).
        overwrite: replace a non-empty ``path``; without ``append`` or ``overwrite`` a
            non-empty file raises FileExistsError.

    Use as a context manager so that a crash still writes the episode's summary::

        with EventLogWrapper(riskflow_env.parallel_env(), "events.jsonl") as env:
            ...
    """

    def __init__(
        self,
        env: Any,
        path: str | os.PathLike | None = None,
        append: bool = False,
        overwrite: bool = False,
    ) -> None:
        require_riskflow_env(env, "EventLogWrapper")
        super().__init__(env)
        self.recorder = EventRecorder(path, append, overwrite)
        self._finalizer = weakref.finalize(self, self.recorder.close, "exit")

    @property
    def events(self) -> list[dict[str, Any]]:
        """Every event so far, summaries included, in order (JSON-ready dicts)."""
        return self.recorder.events

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        result = self.env.reset(seed=seed, options=options)
        base = self.env.unwrapped
        self.recorder.begin(base.scenario.name)
        self.recorder.observe(base.view(), base.last_events)
        return result

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        result = self.env.step(actions)
        base = self.env.unwrapped
        self.recorder.observe(base.view(), base.last_events)
        if not base.agents:
            self.recorder.finish("done")
        return result

    def close(self, reason: str = "close") -> None:
        """Finish the open episode (cause ``reason``), close the log, then the env."""
        self._finalizer.detach()
        self.recorder.close(reason)
        self.env.close()

    def __enter__(self) -> EventLogWrapper:
        return self

    def __exit__(self, exc_type: Any, exc: Any, traceback: Any) -> None:
        self.close("close" if exc_type is None else "exception")


__all__ = ["EventLogWrapper", "EventRecorder", "contact_kind", "contact_point", "read_event_log"]
