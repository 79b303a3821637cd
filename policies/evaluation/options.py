"""``riskflow-eval`` options (a typed dataclass) and the grid of rollouts they ask for.

:class:`EvalOptions` is what the command line fills, its values checked when it is built
(every error names its argument); :func:`plan_jobs` checks the output folder and expands
it into :class:`Job` s, one per (method, K, planning interval, scene, seed). A method
without K (or without a planning interval) gets one job per scene and seed for all K (or
intervals): its key has ``k`` (or ``interval``) None. The run-level settings
(:class:`RunConfig`) must be the same for every row of a results file; the per-job ones
are in each row's key.
"""

from __future__ import annotations

import importlib.util
import json
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from policies.cli_inputs import (
    DT,
    SHIPPED,
    check_device,
    check_interval,
    check_seeds,
    open_data,
)
from policies.dataclass_cli import check_at_least, check_choices, check_field_types, from_fields
from policies.learned.guidance_losses import TARGETS
from policies.planners import PLANNERS
from policies.registry import method_options, method_spec
from riskflow_env.config import MAX_EPISODE_STEPS, EnvConfig, is_integer
from riskflow_env.folder_lock import check_output_folder
from riskflow_env.processes import MAX_WORKERS
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset

SCHEMA = 1  # results.jsonl row layout version


@dataclass(frozen=True)
class EvalOptions:
    """Closed-loop evaluation of scene policies against an ego planner."""

    methods: tuple[str, ...] = ("riskflow",)
    """methods to evaluate (riskflow-eval --list shows them)"""
    k: tuple[str, ...] = ("5",)
    """controllable-set sizes K: ints >= 0 or 'all'"""
    interval: tuple[float, ...] = (0.5,)
    """[s] planning intervals (multiples of the env dt, 0.1 s, up to 5.2 s)"""
    scenes: int | None = None
    """number of scenes, the first ones of the source (not given: all of them; more than it
    holds is an error)"""
    data: str | None = None
    """scene folder: riskflow-data output (.npz) or a ScenarioNet dataset (dataset_summary.pkl,
    read scene by scene); default: the shipped evaluation scenes"""
    seeds: tuple[int, ...] = (0,)
    """rollout seeds, distinct ints >= 0 (one rollout per scene and seed)"""
    ego: str = "idm"
    """ego planner under test, a name of policies.planners.PLANNERS (idm, sampling_mpc...)"""
    target: str = "others"
    """guidance target: 'others' (the paper's) or 'ego'"""
    duration: float = 10.0
    """[s] episode length"""
    stop_at_ego_collision: bool = False
    """end an episode when the ego collides (default: full episodes, equal exposure)"""
    leave_when_log_ends: bool = False
    """a vehicle leaves the scene when its logged track ends, as the recorded ones do at
    the map's exits (EnvConfig.leave_when_log_ends; Waymax's validity rule); off: every
    vehicle stays for the whole episode"""
    diffusion_steps: int | None = None
    """denoising steps of ctg / ctgpp / ccdiff: fewer than 100 run DDIM; default: all 100 (DDPM)"""
    overrides: tuple[str, ...] = field(default=(), metadata={"flag": "--set"})
    """method options key=value or method.key=value (e.g. riskflow.guidance_steps=10)"""
    wosac: bool = True
    """compute the WOSAC-style likelihood per rollout"""
    workers: int = 1
    """worker processes (each with one torch thread), at most 256; 1 runs in this process;
    with --backend ray, the CPUs of the local Ray instance"""
    backend: str = "local"
    """where the rollouts run: 'local' (this process or --workers processes) or 'ray' (Ray
    tasks; needs the ray extra)"""
    address: str | None = None
    """with --backend ray: the Ray cluster to use ('auto', 'ray://host:10001'); default: a
    local Ray with --workers CPUs"""
    device: str = "cpu"
    """torch device of the learned methods"""
    batch_scenes: int = 1
    """rollouts stepped as one batch: up to N scenes of one method, K and interval at once,
    the learned adversaries planning them in one call (docs/tutorials/reproduce.md); 1: one rollout
    at a time"""
    out: str = "outputs/eval"
    """output directory (results.jsonl, samples/, report.md, plots)"""
    report: bool = True
    """write the report when the runs are done"""

    def __post_init__(self) -> None:
        """ValueError naming the argument for a bad value (the values alone: the scene
        source and the output folder are read when the run is prepared, :func:`plan_jobs`;
        the method options ``--set``, which import the methods, there too)."""
        check_field_types(self)
        if not self.methods:
            raise ValueError("--methods: give at least one method")
        for name in self.methods:
            method_spec(name)
        if len(set(self.methods)) != len(self.methods):
            raise ValueError(f"--methods: repeated method in {self.methods}")
        for name in ("k", "interval"):
            if not getattr(self, name):
                raise ValueError(f"--{name}: give at least one value")
        for text in self.k:
            parse_k(text)
        for interval in self.interval:
            check_interval(interval, DT, None)
        check_at_least(self, {"scenes": 1, "diffusion_steps": 1}, ("scenes", "diffusion_steps"))
        workers = self.workers
        if not (is_integer(workers) and 1 <= workers <= MAX_WORKERS):
            raise ValueError(f"--workers must be in [1, {MAX_WORKERS}], got {workers!r}")
        object.__setattr__(self, "workers", int(workers))  # a numpy int as a Python one
        check_batch_scenes(self.batch_scenes, self.backend)
        object.__setattr__(self, "batch_scenes", int(self.batch_scenes))
        check_backend(self.backend, self.address)
        if isinstance(self.ego, str) and ":" in self.ego:  # a spec riskflow-stress takes
            raise ValueError(
                f"--ego must be one of {tuple(PLANNERS)}, got {self.ego!r}: a planner of your "
                "own runs with riskflow-stress --planner FILE.py:OBJECT"
            )
        check_choices(self, {"ego": tuple(PLANNERS), "target": TARGETS})
        check_interval(self.duration, DT, None, "--duration")
        if self.duration / DT > MAX_EPISODE_STEPS:  # checked before anything is written
            raise ValueError(
                f"--duration: {self.duration:g} s is over the longest episode, "
                f"{MAX_EPISODE_STEPS * DT:g} s"
            )
        object.__setattr__(self, "seeds", check_seeds(self.seeds))
        check_device(self.device)


@dataclass(frozen=True)
class Job:
    """One rollout to run: the row key fields and what the worker needs."""

    method: str
    options: dict[str, Any]
    k: int | str | None
    interval: float | None
    scene: str
    scene_index: int
    seed: int
    run: RunConfig
    checkpoint_sha256: str | None = None
    """the weights of ``options["checkpoint"]`` when the run was prepared (not in the key)"""

    @property
    def key(self) -> str:
        """The row's identity in ``results.jsonl``."""
        return row_key(self.method, self.options, self.k, self.interval, self.scene, self.seed)

    @property
    def policy_seed(self) -> int:
        """The policy's noise seed: a function of (seed, scene) only."""
        words = [self.seed, zlib.crc32(self.scene.encode())]
        return int(np.random.SeedSequence(words).generate_state(1)[0])


def row_key(
    method: str,
    options: dict[str, Any],
    k: int | str | None,
    interval: float | None,
    scene: str,
    seed: int,
) -> str:
    """Canonical JSON of (method, options, k, interval, scene, seed)."""
    fields = [method, options, k, interval, scene, seed]
    return json.dumps(fields, sort_keys=True, separators=(",", ":"))


def method_label(method: str, options: dict[str, Any]) -> str:
    """The method's name in tables: ``ctg[sampling_steps=10]``."""
    if not options:
        return method
    return method + "[" + ",".join(f"{k}={v}" for k, v in sorted(options.items())) + "]"


def parse_k(text: str) -> int | str:
    """A ``--k`` value: an int >= 0 or 'all'."""
    if text == "all":
        return text
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise ValueError(f"--k: expected an int >= 0 or 'all', got {text!r}")
    return value


@dataclass(frozen=True)
class RunConfig:
    """The run-level settings of a rollout: what every row of one results file shares
    (``config.json``, :meth:`as_json`), plus how the worker runs it (``wosac``, ``device``:
    not part of the results' identity).

    Attributes:
        data: the scene source (a folder, or ``"shipped:eval"``).
        ego: the ego planner (a name of ``policies.planners.PLANNERS``).
        target: the guidance target (``"others"`` or ``"ego"``).
        duration: rollout length [s].
        stop_at_ego_collision: end the episode at the ego's first collision.
        leave_when_log_ends: vehicles leave the scene when their logged track ends.
        wosac: compute the WOSAC-style score of each rollout.
        device: torch device of the learned policies.
    """

    data: str
    ego: str
    target: str
    duration: float
    stop_at_ego_collision: bool
    wosac: bool = True
    device: str = "cpu"
    leave_when_log_ends: bool = False

    @classmethod
    def from_options(cls, options: EvalOptions) -> RunConfig:
        """The run settings of ``options`` (its fields of the same names)."""
        return from_fields(cls, options, data=options.data or SHIPPED)

    def as_json(self) -> dict[str, Any]:
        """``config.json``: the settings every row of the results file shares."""
        return {
            "schema": SCHEMA,
            "data": self.data,
            "ego": self.ego,
            "target": self.target,
            "duration": self.duration,
            "stop_at_ego_collision": self.stop_at_ego_collision,
            # only when set, so that runs made before the option still resume
            **({"leave_when_log_ends": True} if self.leave_when_log_ends else {}),
        }

    def env_config(self, dt: float) -> EnvConfig:
        """Episode length and termination of the run (full episodes unless stopping at
        an ego collision; nobody ends on leaving the road)."""
        return EnvConfig(
            episode_steps=round(self.duration / dt),
            terminate_on_collision="ego" if self.stop_at_ego_collision else "none",
            terminate_on_offroad="none",
            leave_when_log_ends=self.leave_when_log_ends,
        )


def scene_names(data: str | None, count: int | None = None) -> list[str]:
    """The names of the first ``count`` scenes (default: all) of ``data`` (see
    :func:`open_data`); ValueError naming ``--scenes`` when the source holds fewer, or
    ``--data`` when one of those scenes' files is missing. Reads no ScenarioNet scene."""
    scenes = open_data(data)
    if count is None:
        count = len(scenes)
    if count > len(scenes):
        source = "the shipped evaluation bank" if data in (None, SHIPPED) else f"--data {data}"
        raise ValueError(
            f"--scenes {count}: {source} holds only {len(scenes)} scenes; "
            f"give --scenes {len(scenes)} or fewer"
        )
    if isinstance(scenes, ScenarioNetDataset):
        missing = scenes.subset(range(count)).missing_files()
        if missing:
            raise ValueError(f"--data: {len(missing)} scenario file(s) missing, e.g. {missing[0]}")
    return list(scenes.names[:count])


def check_options(options: EvalOptions) -> None:
    """ValueError naming ``--out`` when it cannot be made a folder: checked when the run
    is prepared, as the disk may change after the options are built (their values were
    checked then, by :class:`EvalOptions`)."""
    check_output_folder(options.out, "--out")


BACKENDS = ("local", "ray")


def check_backend(backend: str, address: str | None) -> None:
    """ValueError naming ``--backend`` / ``--address`` when they do not fit together or Ray
    is missing."""
    if backend not in BACKENDS:
        raise ValueError(f"--backend must be one of {BACKENDS}, got {backend!r}")
    if address is not None and backend != "ray":
        raise ValueError("--address is a Ray cluster address: give it with --backend ray")
    if backend == "ray" and importlib.util.find_spec("ray") is None:
        raise ValueError("--backend ray needs Ray: pip install -e '.[ray]'")


def check_batch_scenes(batch_scenes: int, backend: str) -> None:
    """ValueError naming ``--batch-scenes`` unless it is an int >= 1, and 1 with Ray."""
    if not is_integer(batch_scenes) or batch_scenes < 1:
        raise ValueError(f"--batch-scenes must be an int >= 1, got {batch_scenes!r}")
    if batch_scenes > 1 and backend == "ray":
        raise ValueError(
            f"--batch-scenes {batch_scenes} runs batches in local processes; --backend ray "
            "runs every rollout as its own task: give --batch-scenes 1 with --backend ray"
        )


def plan_jobs(options: EvalOptions, scenes: Sequence[str]) -> list[Job]:
    """Every rollout the options ask for, in a fixed order (ValueError on bad arguments);
    ``scenes``: the names of the scenes (:func:`scene_names`), in order."""
    check_options(options)
    ks = list(dict.fromkeys(parse_k(text) for text in options.k))
    intervals = list(dict.fromkeys(check_interval(t, DT, None) for t in options.interval))
    per_method = method_options(options.methods, options.overrides, options.diffusion_steps)
    run = RunConfig.from_options(options)
    jobs = []
    for method in options.methods:
        spec = method_spec(method)
        for k in ks if spec.uses_k else [None]:
            for interval in intervals if spec.uses_interval else [None]:
                for index, scene in enumerate(scenes):
                    for seed in options.seeds:
                        job = Job(method, per_method[method], k, interval, scene, index, seed, run)
                        jobs.append(job)
    if len(set(scenes)) != len(scenes):
        raise ValueError("--data: scene names must be unique (they key the results rows)")
    return list({job.key: job for job in jobs}.values())
