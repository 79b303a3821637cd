"""Checkpoints a Stable-Baselines3 run resumes from, and a clean stop on Ctrl-C / SIGTERM.

:class:`RunCheckpoints` (a callback) keeps, at the start of every rollout, what the learner
holds right after its last update: the weights and Adam moments (in the model), the
decisions done, the ``VecNormalize`` statistics and the states of the random generators
(``random``, numpy's global one, torch's CPU one). It writes them
(:func:`~policies.rl.runs.checkpoint_files`) at the first rollout start at or after every
``every`` decisions, at the end of training (whatever ``every``), and, when
:class:`StopSignals` caught SIGINT or SIGTERM, as of the last rollout start (the
unfinished rollout is dropped: it has not been learned from). :func:`resume` puts a
checkpoint back into a model built on fresh envs.

What a resume does not restore: the episodes in flight (SB3 saves no env state, and the
envs may live in worker processes). The resumed run starts fresh episodes, seeded from
the run's seed and the decisions done; so two resumes of one checkpoint agree bit for bit,
but neither is an uninterrupted run: they differ from it from the first rollout after
the checkpoint. ``VecNormalize``'s per-env discounted return (which SB3 does not pickle)
restarts at 0, as it does for any fresh episode.

Needs the ``rl`` extra (stable-baselines3).
"""

from __future__ import annotations

import base64
import json
import pickle
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback

from policies.rl.runs import Checkpoint, checkpoint_files
from policies.rl.signals import StopSignals
from riskflow_env.atomic_files import atomic_path, write_bytes, write_text


def save_model(model: Any, path: Path) -> None:
    """``path.zip`` and, with VecNormalize, ``path_vecnormalize.pkl``."""
    model.save(path)
    normalize = model.get_vec_normalize_env()
    if normalize is not None:
        normalize.save(str(path.with_name(path.name + "_vecnormalize.pkl")))


def rng_state() -> dict[str, Any]:
    """The states of ``random``, numpy's global generator and torch's CPU generator, as
    JSON values."""
    name, keys, position, has_gauss, gauss = np.random.get_state(legacy=True)  # noqa: NPY002 - SB3 seeds it
    version, internal, cached = random.getstate()
    return {
        "random": [version, list(internal), cached],
        "numpy": [name, keys.tolist(), position, has_gauss, gauss],
        "torch": base64.b64encode(torch.get_rng_state().numpy().tobytes()).decode("ascii"),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore :func:`rng_state`'s generators."""
    version, internal, cached = state["random"]
    random.setstate((version, tuple(internal), cached))
    name, keys, position, has_gauss, gauss = state["numpy"]
    numpy_state = (name, np.array(keys, dtype=np.uint32), position, has_gauss, gauss)
    np.random.set_state(numpy_state)  # noqa: NPY002 - the generator SB3 seeds
    raw = np.frombuffer(base64.b64decode(state["torch"]), dtype=np.uint8).copy()
    torch.set_rng_state(torch.from_numpy(raw))


class RunCheckpoints(BaseCallback):
    """Resumable checkpoints every ``every`` decisions, at the end of training, and on a
    stop signal (module docstring).

    Args:
        folder: where the checkpoints go (``RUN/checkpoints``).
        every: decisions between checkpoints (0: none, except on a stop signal).
        stop: the signals to stop on, or None.
    """

    def __init__(self, folder: Path, every: int, stop: StopSignals | None = None) -> None:
        super().__init__()
        self.folder, self.every, self.stop = Path(folder), int(every), stop
        self.boundary: dict[str, Any] | None = None  # the learner at the last rollout start
        self.saved: int | None = None  # decisions of the last checkpoint written
        self.next_due = 0

    @property
    def stopped(self) -> bool:
        return self.stop is not None and self.stop.received is not None

    def _on_training_start(self) -> None:
        self.next_due = self._after(self.model.num_timesteps)

    def _on_rollout_start(self) -> None:
        self.boundary = self._learner()
        if self.every > 0 and self.model.num_timesteps >= self.next_due:
            self._save(self.boundary)

    def _on_step(self) -> bool:
        return not self.stopped

    def _on_training_end(self) -> None:
        if self.stopped and self.boundary is not None:
            self.model.num_timesteps = self.boundary["decisions"]  # the partial rollout goes
            if self.saved != self.boundary["decisions"]:
                self._save(self.boundary)
        elif not self.stopped and self.saved != self.model.num_timesteps:
            self._save(self._learner())  # the end: what a longer --resume goes on from

    def _after(self, decisions: int) -> int:
        """The first multiple of ``every`` above ``decisions``."""
        return (decisions // self.every + 1) * self.every if self.every > 0 else 0

    def _learner(self) -> dict[str, Any]:
        """What a checkpoint holds besides the model: decisions, generators, statistics."""
        normalize = self.model.get_vec_normalize_env()
        return {
            "decisions": int(self.model.num_timesteps),
            "rng": rng_state(),
            "stats": None if normalize is None else pickle.dumps(normalize),
        }

    def _save(self, learner: dict[str, Any]) -> None:
        decisions = learner["decisions"]
        model_path, stats_path, state_path = checkpoint_files(self.folder, decisions)
        self.folder.mkdir(parents=True, exist_ok=True)
        # The model file, found by its name, comes last and appears whole (written aside,
        # then renamed): a save cut short by a second signal leaves no checkpoint that
        # lacks its statistics or state.
        if learner["stats"] is not None:
            write_bytes(stats_path, learner["stats"])
        state = {"decisions": decisions, "rng": learner["rng"]}
        write_text(state_path, json.dumps(state))
        with atomic_path(model_path, suffix=".zip") as aside:  # ".ppo_...": not a checkpoint name
            self.model.save(aside)
        self.saved, self.next_due = decisions, self._after(decisions)


def resume(model: Any, checkpoint: Checkpoint, seed: int) -> None:
    """Make ``model`` (loaded from ``checkpoint.model`` on fresh envs) continue from the
    checkpoint: its envs re-seeded with ``seed + decisions`` (fresh episodes: module
    docstring) and the random generators as they were when it was saved."""
    model.get_env().seed(seed + checkpoint.decisions)
    if checkpoint.state is not None:
        set_rng_state(json.loads(checkpoint.state.read_text(encoding="utf-8"))["rng"])


def keep_progress_rows(path: Path, decisions: int) -> tuple[list[str], list[str]]:
    """The header and the rows of SB3's ``progress.csv`` logged at or before ``decisions``
    (``time/total_timesteps``): what a resume from that checkpoint keeps of the log."""
    import csv

    if not Path(path).is_file():
        return [], []
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    if not lines:
        return [], []
    header = next(csv.reader([lines[0]]))
    if "time/total_timesteps" not in header:
        return header, lines[1:]
    column = header.index("time/total_timesteps")
    kept = []
    for line in lines[1:]:
        row = next(csv.reader([line]), [])
        if len(row) > column and row[column] and float(row[column]) <= decisions:
            kept.append(line)
    return header, kept


def restore_progress_rows(logger: Any, kept: tuple[list[str], list[str]]) -> None:
    """Write ``kept`` (:func:`keep_progress_rows`) back at the top of the logger's fresh CSV
    file (SB3 opens it with mode ``w+``), so that the resumed run's rows follow them."""
    from stable_baselines3.common.logger import CSVOutputFormat

    header, rows = kept
    if not header:
        return
    for output in logger.output_formats:
        if isinstance(output, CSVOutputFormat):
            output.file.write(",".join(header) + "\n")
            output.file.writelines(row + "\n" for row in rows)
            output.file.flush()
            output.keys = list(header)
