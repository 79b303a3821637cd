"""The event log on disk: a JSON Lines file read back, and prepared for appending.

:func:`read_event_log` reads the events of a log in order; a torn final line (a run
killed mid-write) is skipped with a warning. A run that appends to an existing log
(``EventRecorder(path, append=True)``) first drops such a torn tail
(:func:`drop_torn_tail`) and continues the episode numbers after the file's last one
(:func:`last_episode`).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

from riskflow_env.folder_lock import file_path


def read_event_log(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The events of a JSON Lines log, in order (blank lines skipped).

    A torn final line (a run killed mid-write: no newline at the end and not valid JSON)
    is skipped with a warning; a bad line anywhere else raises ValueError naming it, and so
    does a file that is not text."""
    file_path(path)
    try:
        with open(path, encoding="utf-8") as file:
            lines = file.read().split("\n")
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not an event log (JSON Lines text): not UTF-8") from None
    events = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError as error:
            if number == len(lines):  # the last line, without its newline: torn
                warnings.warn(
                    f"{path}: skipping a torn last line (line {number}: {line[:60]!r})",
                    UserWarning,
                    stacklevel=2,
                )
                break
            raise ValueError(f"{path}: line {number} is not valid JSON ({error})") from None
    return events


def check_event_log(path: Path) -> None:
    """ValueError naming ``path`` unless its first line is an event row (a JSON object
    with an ``event`` field): appending must not truncate or extend another file."""
    with open(path, "rb") as file:
        first = b""
        while not first and (line := file.readline(1 << 16)):  # blank lines skipped
            first = line.strip()
    try:
        row = json.loads(first)
    except ValueError:  # a first row torn by a kill: every row starts with its event
        row = {"event": None} if first.startswith(b'{"event": ') else None
    if not (isinstance(row, dict) and "event" in row):
        raise ValueError(
            f"{path} is not an event log (its first line is not an event row): refusing to "
            "append to it"
        )


def drop_torn_tail(path: Path) -> None:
    """Truncate ``path`` after its last newline (a killed run's partial line), warning."""
    with open(path, "rb+") as file:
        file.seek(0, os.SEEK_END)
        size = file.tell()
        if size == 0:
            return
        file.seek(max(size - 1, 0))
        if file.read(1) == b"\n":
            return
        file.seek(0)
        data = file.read()
        keep = data.rfind(b"\n") + 1
        warnings.warn(
            f"{path}: dropping a torn last line ({size - keep} bytes) before appending",
            UserWarning,
            stacklevel=3,
        )
        file.truncate(keep)


def last_episode(path: Path) -> int:
    """The ``episode`` of the last event in ``path`` (-1 if none), read line by line."""
    last = b""
    with open(path, "rb") as file:
        for line in file:
            if line.strip():
                last = line
    try:
        episode = json.loads(last)["episode"] if last else -1
    except (ValueError, KeyError, TypeError):
        return -1
    return episode if isinstance(episode, int) and not isinstance(episode, bool) else -1


__all__ = ["check_event_log", "drop_torn_tail", "last_episode", "read_event_log"]
