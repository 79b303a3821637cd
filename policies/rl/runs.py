"""A training run folder of ``examples/train_ego_ppo.py``: what it holds and finding its models.

::

    RUN/
      options.json                      the script's options (what --resume reads)
      initial_model.zip                 the untrained policy (+ initial_model_vecnormalize.pkl)
      final_model.zip                   written when training completes (+ _vecnormalize.pkl)
      checkpoints/ppo_N_steps.zip       every --checkpoint-every decisions and on Ctrl-C /
                                        SIGTERM, with ppo_vecnormalize_N_steps.pkl and
                                        ppo_state_N_steps.json (policies.rl.checkpoints)
      progress.csv, training.png        SB3's CSV log and the training curves

:func:`find_model` turns what a user names (a run folder, or a model file with or without
``.zip``) into the model file and its run folder, or a :class:`RunError` whose message
names the argument and what was expected: the evaluation and the training scripts print it
as one line. Nothing here unpickles a file (a model's zip is opened only to list it).
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import sys
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from policies.dataclass_cli import dataclass_parser, field_values
from riskflow_env.folder_lock import make_output_folder

OPTIONS = "options.json"
FINAL = "final_model"
INITIAL = "initial_model"
CHECKPOINTS = "checkpoints"
_CHECKPOINT = re.compile(r"ppo_(\d+)_steps\.zip")


class RunError(ValueError):
    """A path that is not what a run folder or a model file should be (message: one line)."""


@dataclass(frozen=True)
class Checkpoint:
    """One checkpoint of a run: ``checkpoints/ppo_N_steps.*``.

    Attributes:
        decisions: policy decisions trained when it was saved (N).
        model: the SB3 model file (``.zip``).
        stats: the VecNormalize statistics (``.pkl``), None when the run does not normalise.
        state: the resume state (``.json``: random generators), None for checkpoints
            written before it existed.
    """

    decisions: int
    model: Path
    stats: Path | None
    state: Path | None


def checkpoint_files(folder: Path, decisions: int) -> tuple[Path, Path, Path]:
    """The (model, VecNormalize statistics, state) paths of checkpoint N in ``folder``
    (SB3's ``CheckpointCallback`` names for the first two)."""
    return (
        folder / f"ppo_{decisions}_steps.zip",
        folder / f"ppo_vecnormalize_{decisions}_steps.pkl",
        folder / f"ppo_state_{decisions}_steps.json",
    )


def checkpoints(run: Path) -> list[Checkpoint]:
    """The run's checkpoints, fewest decisions first."""
    found = []
    for path in (Path(run) / CHECKPOINTS).glob("ppo_*_steps.zip"):
        match = _CHECKPOINT.fullmatch(path.name)
        if match:
            model, stats, state = checkpoint_files(path.parent, int(match.group(1)))
            found.append(
                Checkpoint(
                    int(match.group(1)),
                    model,
                    stats if stats.is_file() else None,
                    state if state.is_file() else None,
                )
            )
    return sorted(found, key=lambda checkpoint: checkpoint.decisions)


def run_begun(run: Path) -> bool:
    """Whether ``run`` holds trained weights: a checkpoint or a final model."""
    checkpoints = run / CHECKPOINTS
    return (run / f"{FINAL}.zip").exists() or (checkpoints.is_dir() and any(checkpoints.iterdir()))


def make_run_folder(out: Path) -> None:
    """Make the folder of a new run, or a :class:`RunError` naming ``--out`` when it holds
    a begun run (:func:`run_begun`: its checkpoints would mix with the new run's) or
    cannot be a folder. A folder whose run never trained (``options.json`` alone) is
    reused."""
    if out.is_dir() and run_begun(out):
        way_out = f"continue it with --resume {out}" if (out / OPTIONS).is_file() else "remove it"
        raise RunError(
            f"--out {out} holds a trained run already: {way_out}, or choose another --out"
        )
    try:
        make_output_folder(out, "--out")
    except ValueError as error:
        raise RunError(str(error)) from None


def check_resume(saved: Path, resume: bool) -> None:
    """For a training script whose run is the file or folder ``saved`` in ``--out``: a
    ValueError for ``--resume`` without it, or for a new run that would overwrite it."""
    if resume and not saved.exists():
        raise ValueError(f"--resume: no checkpoint in {saved}")
    if not resume and saved.exists():
        raise ValueError(
            f"--out {saved.parent} holds a run already: continue it with --resume, or choose "
            "another --out"
        )


def read_options(run: Path, argument: str = "--runs") -> dict[str, Any]:
    """The run's ``options.json`` as a dict; a :class:`RunError` naming ``argument`` when
    ``run`` is not a run folder."""
    run = Path(run)
    if run.is_file():
        raise RunError(f"{argument} {run}: a file, not a run folder")
    if not run.is_dir():
        raise RunError(f"{argument} {run}: no such run folder")
    path = run / OPTIONS
    if not path.is_file():
        raise RunError(
            f"{argument} {run}: not a training run folder (no {OPTIONS}; "
            "examples/train_ego_ppo.py --out writes one)"
        )
    try:
        options = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise RunError(f"{argument} {run}: {OPTIONS} is not valid JSON ({error})") from None
    if not isinstance(options, dict) or "seed" not in options:
        raise RunError(f"{argument} {run}: {OPTIONS} is not a train_ego_ppo.py options file")
    return options


def check_model_file(path: Path, argument: str) -> Path:
    """``path`` if it is an SB3 model file (a zip with a ``data`` member), else a
    :class:`RunError` naming ``argument``. Lists the zip; unpickles nothing."""
    if not zipfile.is_zipfile(path):
        raise RunError(f"{argument} {path}: not a stable-baselines3 model file (not a zip file)")
    with zipfile.ZipFile(path) as archive:
        if "data" not in archive.namelist():
            raise RunError(
                f"{argument} {path}: not a stable-baselines3 model file (no 'data' member)"
            )
    return path


@dataclass(frozen=True)
class RunModel:
    """A model to evaluate and the run it belongs to.

    Attributes:
        run: the run folder (its ``options.json`` and ``initial_model.zip``).
        model: the model file.
        note: why this model was chosen when the user did not name it ('' otherwise).
    """

    run: Path
    model: Path
    note: str = ""


def find_model(entry: str | Path, model: str = FINAL, argument: str = "--runs") -> RunModel:
    """The model named by ``entry``: a run folder (its ``model``, by default
    ``final_model``; an interrupted run without one: its latest checkpoint), or a model
    file given with or without ``.zip`` (its run: the folder holding it, or the one above
    its ``checkpoints/``). A :class:`RunError` naming ``argument`` (or ``--model``) when
    there is no such folder or file, or it is not what it should be."""
    path = Path(entry)
    stem = model.removesuffix(".zip")
    if path.is_dir():
        read_options(path, argument)
        chosen = path / f"{stem}.zip"
        if chosen.is_file():
            return RunModel(path, check_model_file(chosen, argument))
        latest = checkpoints(path)
        if stem != FINAL or not latest:
            raise RunError(f"--model {model}: {chosen} does not exist (run {path})")
        last = latest[-1]
        note = (
            f"{path}: no {FINAL}.zip (interrupted or still training): evaluating its latest "
            f"checkpoint, {CHECKPOINTS}/{last.model.name} ({last.decisions} decisions)"
        )
        return RunModel(path, check_model_file(last.model, argument), note)
    candidates = [path, path.with_name(path.name + ".zip")] if path.name else [path]
    file = next((candidate for candidate in candidates if candidate.is_file()), None)
    if file is None:
        raise RunError(f"{argument} {entry}: no such run folder or model file")
    check_model_file(file, argument)
    for run in (file.parent, file.parent.parent):
        if (run / OPTIONS).is_file():
            read_options(run, argument)
            return RunModel(run, file)
    raise RunError(
        f"{argument} {entry}: no {OPTIONS} beside the model or above its {CHECKPOINTS}/ folder "
        "(the run's options tell how the policy observes and acts)"
    )


def latest_checkpoint(run: Path) -> Checkpoint | None:
    """The run's checkpoint with the most decisions, or None."""
    found = checkpoints(run)
    return found[-1] if found else None


def final_from_checkpoint(run: Path, checkpoint: Checkpoint) -> Path:
    """The run's final model: written from ``checkpoint`` (the model and its normalisation
    statistics) if the run stopped after its last checkpoint and before its final model."""
    final = run / f"{FINAL}.zip"
    if not final.is_file():
        shutil.copyfile(checkpoint.model, final)
        if checkpoint.stats is not None and checkpoint.stats.is_file():
            shutil.copyfile(checkpoint.stats, run / f"{FINAL}_vecnormalize.pkl")
        print(f"final model: {final}, from {checkpoint.model.name}")
    return final


def parse_resumable(
    cls: type,
    argv: Sequence[str] | None,
    prog: str,
    description: str,
    changeable: tuple[str, ...],
) -> Any:
    """Options of a training script whose dataclass ``cls`` has ``resume`` and ``out``
    fields (:func:`policies.dataclass_cli.parse_dataclass` otherwise). With ``--resume
    RUN``, the run's ``options.json`` gives the defaults, ``out`` is RUN, and a flag that
    changes an option outside ``changeable`` is a usage error naming it: a resumed run
    keeps what its model was built with."""
    parser = dataclass_parser(cls, prog, description)
    argv = sys.argv[1:] if argv is None else list(argv)
    run = parser.parse_known_args(argv)[0].resume
    stored: dict[str, Any] = {}
    if run is not None:
        names = {field.name for field in dataclasses.fields(cls)}
        try:
            raw = read_options(run, "--resume")
            stored = field_values(cls, {k: v for k, v in raw.items() if k in names})
        except ValueError as error:  # RunError included: one line, no usage
            print(f"{prog}: error: {error}", file=sys.stderr)
            sys.exit(2)
        parser.set_defaults(**stored)
    values = vars(parser.parse_args(argv))
    try:
        options = cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
    except ValueError as error:
        parser.error(str(error))
    if run is None:
        return options
    fixed = [name for name in stored if name not in (*changeable, "out", "resume")]
    changed = [name for name in fixed if getattr(options, name) != stored[name]]
    if changed:
        flags = ", ".join(
            f"--{name.replace('_', '-')} {getattr(options, name)} (the run's: {stored[name]})"
            for name in changed
        )
        allowed = ", ".join(f"--{name.replace('_', '-')}" for name in changeable)
        parser.error(
            f"--resume {run}: a resumed run keeps its options; {flags} given; "
            f"only {allowed} may change"
        )
    return dataclasses.replace(options, out=Path(run))
