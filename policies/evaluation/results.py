"""The results folder: ``config.json``, ``results.jsonl`` (one row per rollout), ``samples/``.

Writing is crash-safe and resumable:

* ``config.json`` holds the run-level settings (:meth:`~.options.RunConfig.as_json`); a run
  with other settings into the same folder is refused (:class:`ConfigMismatch`), never
  mixed in. It also records the weights of every checkpoint file a method was given
  (``checkpoints``), so rows of a checkpoint retrained in place are never reused.
* Each finished rollout first writes its KDD samples to ``samples/<id>.npz`` (temporary
  file, fsync, rename), then appends its row to ``results.jsonl`` and fsyncs. The row is
  the commit: a rollout interrupted before its row is written is simply run again.
* :meth:`ResultsStore.done_keys` reads the keys of the rows present; a torn last line
  (a crash mid-write) is ignored and overwritten on the next append.
* One writer per folder: the first write takes the folder's
  :class:`~riskflow_env.folder_lock.FolderLock` (``writer.lock``, holding the writer's
  pid). A second run into the same folder gets :class:`ResultsLocked`; the OS releases
  the lock when the writer ends, ``kill -9`` included, so a killed run never blocks its
  resume.
* Reading keeps the first row of each key (a folder written by two runs at once before
  the lock existed counts each rollout once) and warns about the duplicates.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.atomic_files import write_bytes
from riskflow_env.folder_lock import FolderLock, FolderLocked
from riskflow_env.metrics import KinematicSamples

RESULTS = "results.jsonl"
CONFIG = "config.json"
CHECKPOINTS = "checkpoints"  # config.json: {checkpoint option as given: weights_sha256}
SAMPLES = "samples"


class ConfigMismatch(ValueError):
    """The output folder holds results of another run configuration."""


class ResultsLocked(FolderLocked):
    """Another process is writing into the output folder."""


def sample_id(key: str) -> str:
    """File stem of a row's samples: a hash of its key."""
    return hashlib.sha1(key.encode()).hexdigest()[:20]


class ResultsStore:
    """One results folder (module docstring).

    Args:
        out: the folder (created when needed).
    """

    def __init__(self, out: str | os.PathLike) -> None:
        self.out = Path(out)
        self.results = self.out / RESULTS
        self.config_file = self.out / CONFIG
        self._lock = FolderLock(self.out)

    def lock(self) -> None:
        """Become the folder's only writer (module docstring); ResultsLocked naming the
        other writer's pid if another process holds the lock. Writing methods call it."""
        try:
            self._lock.acquire()
        except FolderLocked as err:
            raise ResultsLocked(f"--out {err}") from None

    def unlock(self) -> None:
        """Release the writer lock (if held); the lock file stays."""
        self._lock.release()

    def check_config(
        self, config: dict[str, Any], checkpoints: dict[str, str] | None = None
    ) -> None:
        """Write ``config.json`` if absent; ConfigMismatch naming the settings that differ.

        ``checkpoints`` maps each ``checkpoint`` option of the run's methods (the path as
        given, as in the rows' keys) to its ``weights_sha256``. They are kept under
        ``config.json``'s ``checkpoints``: a path new to the folder (or with no row yet) is
        recorded, and a path whose weights changed since its rows were written (a
        checkpoint retrained in place) is refused with ConfigMismatch, since its rows
        would otherwise be reused."""
        self.lock()
        checkpoints = dict(checkpoints or {})
        if not self.config_file.exists():
            self._write_config({**config, **({CHECKPOINTS: checkpoints} if checkpoints else {})})
            return
        stored = self.config()
        known = stored.pop(CHECKPOINTS, {})
        differ = sorted(k for k in set(stored) | set(config) if stored.get(k) != config.get(k))
        if differ:
            details = ", ".join(
                f"{k}: {stored.get(k)!r} there, {config.get(k)!r} now" for k in differ
            )
            raise ConfigMismatch(
                f"--out {self.out} holds results of another configuration ({details}); "
                "use another --out, or the same settings to resume"
            )
        changed = sorted(
            path for path in checkpoints if known.get(path, checkpoints[path]) != checkpoints[path]
        )
        used = {str(row["options"].get("checkpoint")) for row in self.rows() if row.get("options")}
        changed = [path for path in changed if path in used]  # no row of it yet: record anew
        if changed:
            path = changed[0]
            raise ConfigMismatch(
                f"--out {self.out} holds rows of checkpoint {path} with other weights "
                f"(weights_sha256 {known[path][:12]} there, {checkpoints[path][:12]} now: "
                "the file changed since); use another --out to evaluate the new weights"
            )
        if any(known.get(path) != digest for path, digest in checkpoints.items()):
            self._write_config({**stored, CHECKPOINTS: {**known, **checkpoints}})

    def _write_config(self, config: dict[str, Any]) -> None:
        write_bytes(self.config_file, json.dumps(config, indent=1, sort_keys=True).encode())

    def config(self) -> dict[str, Any]:
        """The stored run configuration ({} if none)."""
        return json.loads(self.config_file.read_text()) if self.config_file.exists() else {}

    def rows(self) -> list[dict[str, Any]]:
        """Every complete row, the first of each key (a torn last line is skipped)."""
        if not self.results.exists():
            return []
        rows: dict[str, dict[str, Any]] = {}
        duplicates = 0
        for line in self.results.read_bytes().split(b"\n"):
            if line.strip():
                try:
                    row = json.loads(line)
                except json.JSONDecodeError:
                    continue  # a torn line from an interrupted write
                if row["key"] in rows:
                    duplicates += 1
                else:
                    rows[row["key"]] = row
        if duplicates:
            warnings.warn(
                f"{self.results}: {duplicates} duplicate row(s) ignored (the same rollout "
                "written twice, e.g. by two runs into one --out)",
                UserWarning,
                stacklevel=2,
            )
        return list(rows.values())

    def done_keys(self) -> set[str]:
        """Keys of the rows present."""
        return {row["key"] for row in self.rows()}

    def append(self, row: dict[str, Any], samples: dict[str, np.ndarray]) -> None:
        """Write one rollout: its samples, then its row (both fsynced)."""
        self.lock()
        name = sample_id(row["key"])
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **{k: np.asarray(v, np.float32) for k, v in samples.items()})
        (self.out / SAMPLES).mkdir(parents=True, exist_ok=True)
        write_bytes(self.out / SAMPLES / f"{name}.npz", buffer.getvalue())
        row = {**row, "samples": f"{SAMPLES}/{name}.npz"}
        line = json.dumps(row, sort_keys=True, allow_nan=False).encode() + b"\n"
        with open(self.results, "ab") as file:
            if file.tell() and not _ends_with_newline(self.results):
                file.write(b"\n")  # after a torn line, start a fresh one
            file.write(line)
            file.flush()
            os.fsync(file.fileno())

    def samples(self, row: dict[str, Any]) -> KinematicSamples:
        """The KDD samples of a row."""
        with np.load(self.out / row["samples"]) as arrays:
            return KinematicSamples.from_arrays({k: arrays[k].astype(np.float64) for k in arrays})


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as file:
        file.seek(-1, os.SEEK_END)
        return file.read(1) == b"\n"
