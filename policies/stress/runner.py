"""``riskflow_stress``: stress-test a planner on many scenes and seeds, in worker processes.

Every (scene, seed) pair is one episode (:mod:`policies.stress.episode`); the jobs run in
this process (``workers=1``) or in ``workers`` spawned processes, each with its own planner
(loaded again from its spec, or unpickled) and its own adversary. An episode depends on its
scene and seed only, so the results, in job order (scenes outer, seeds inner), are those of
``workers=1`` whatever the worker count (wall times aside). With an output folder, each
episode's row is appended to ``episodes.jsonl`` and each failure saved as a replay file as
soon as the episode returns (:mod:`policies.stress.outputs`).
"""

from __future__ import annotations

import multiprocessing
import pickle
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from policies.cli_inputs import check_device, check_seeds, open_data
from policies.dataclass_cli import check_at_least
from policies.planners import EgoPlanner, reset_planner
from policies.planners.base import as_action
from policies.stress.episode import EpisodeRunner, EpisodeSetup
from policies.stress.planner_spec import load_planner
from policies.stress.summary import Analysed
from riskflow_env.cli_errors import interrupt_of
from riskflow_env.config import is_integer
from riskflow_env.processes import pool_worker
from riskflow_env.scenarios import Scenario


@dataclass(frozen=True)
class StressOptions(EpisodeSetup):
    """Options of a stress test: the episode setup, the scenes and seeds, how to run."""

    scenes: int = 20
    """scenes to run: the first N of the shipped evaluation bank (105) or of --data"""
    data: Path | None = None
    """a folder of .npz scenes or a ScenarioNet dataset; default the shipped evaluation bank"""
    seeds: tuple[int, ...] = (0,)
    """adversary noise seeds; every scene runs once per seed"""
    workers: int = 1
    """worker processes (each its own planner and adversary); the results do not depend on it"""
    out: Path = Path("outputs/stress")
    """output folder: summary.json, episodes.jsonl, report.md, report.html, failures/, gifs/"""
    gifs: int = 3
    """worst failures drawn as GIFs in the report (0: none)"""
    progress: bool = True
    """show a progress bar with ETA"""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_at_least(self, {"scenes": 1, "workers": 1, "gifs": 0})
        object.__setattr__(self, "seeds", check_seeds(self.seeds))
        if self.data is not None:
            object.__setattr__(self, "data", Path(self.data))
        object.__setattr__(self, "out", Path(self.out))
        check_device(self.device)

    def setup(self) -> EpisodeSetup:
        """The episode setup alone."""
        return EpisodeSetup.from_json(self.as_json())


@dataclass(frozen=True)
class Episode:
    """One finished job: the scene's position in the run, the seed, the analysed episode,
    and its replay file (None without a failure or an output folder)."""

    index: int
    seed: int
    analysed: Analysed
    replay: Path | None = None


class SceneSourceError(ValueError):
    """The scenes asked for are not there (the message names ``--scenes`` or ``--data``)."""


@dataclass(frozen=True)
class Scenes:
    """Where the jobs' scenes come from: a ``data`` source (None: the shipped bank) read by
    index in each process, or explicit scenarios (pickled to the workers)."""

    data: Path | None = None
    scenarios: tuple[Scenario, ...] = ()
    count: int = 0

    def open(self) -> Sequence[Scenario]:
        if self.scenarios:
            return self.scenarios
        try:
            return open_data(self.data)
        except ValueError as err:  # names --data
            raise SceneSourceError(str(err)) from err

    @classmethod
    def of(cls, scenes: int | Sequence[Scenario], data: Path | None) -> Scenes:
        """``scenes`` (a count of ``data``'s first scenes, or the scenarios);
        :class:`SceneSourceError` naming ``--scenes`` when the source holds fewer, or
        ``--data`` when it is not a folder of scenes."""
        if not is_integer(scenes):
            scenarios = tuple(scenes)
            if not scenarios or not all(isinstance(s, Scenario) for s in scenarios):
                raise SceneSourceError("scenes must be an int >= 1 or a list of Scenario")
            return cls(scenarios=scenarios, count=len(scenarios))
        available = len(cls(data=data).open())
        if scenes > available:
            source = "the shipped evaluation bank" if data is None else f"--data {data}"
            raise SceneSourceError(
                f"--scenes {scenes}: {source} holds only {available} scenes; give "
                f"--scenes {available} or fewer"
            )
        return cls(data=data, count=scenes)


@dataclass
class _Worker:
    """What a process needs to run jobs (built once per process)."""

    planner: str | bytes | EgoPlanner
    setup: EpisodeSetup
    scenes: Scenes
    runner: EpisodeRunner | None = None
    opened: Sequence[Scenario] = field(default_factory=tuple)
    guarded: GuardedPlanner | None = None

    def __call__(self, job: tuple[int, int]) -> Episode:
        if self.runner is None:
            self.guarded = GuardedPlanner(resolve_planner(self.planner, self.setup))
            self.runner = EpisodeRunner(self.guarded, self.setup)
            self.opened = self.scenes.open()
        index, seed = job
        self.guarded.where = f"scene {index} ({self.opened[index].name}), seed {seed}"
        return Episode(index, seed, self.runner(self.opened[index], seed))


class PlannerError(ValueError):
    """The planner under test raised; the message says what, in which episode and step."""


class GuardedPlanner:
    """The planner under test, its exceptions turned into a :class:`PlannerError` that
    names the episode (``where``) and the step."""

    def __init__(self, planner: EgoPlanner) -> None:
        self.planner, self.where = planner, ""

    def __call__(self, observation: Any, view: Any) -> Any:
        return self._guard(lambda: as_action(self.planner(observation, view)), view)

    def reset(self, view: Any) -> None:
        self._guard(lambda: reset_planner(self.planner, view), view)

    def _guard(self, call: Callable[[], Any], view: Any) -> Any:
        try:
            return call()
        except Exception as err:
            if interrupt_of(err) is not None:  # Ctrl-C inside a compiled planner
                raise
            step = getattr(view, "step", "?")
            raise PlannerError(
                f"the planner raised {type(err).__name__}: {err} ({self.where}, step {step})"
            ) from err


_WORKER: _Worker | None = None


def _init_worker(worker: _Worker) -> None:
    global _WORKER
    pool_worker()  # a killed run leaves no worker behind; Ctrl-C is the parent's
    _WORKER = worker


def _run_job(job: tuple[int, int]) -> Episode:
    return _WORKER(job)


def resolve_planner(planner: str | bytes | EgoPlanner, setup: EpisodeSetup) -> EgoPlanner:
    """The planner of a spec (loaded fresh), of pickled bytes, or the object itself."""
    if isinstance(planner, str):
        return load_planner(planner, setup.env_config().dynamics, argument="planner")
    if isinstance(planner, bytes):
        return pickle.loads(planner)
    return planner


def portable_planner(planner: str | EgoPlanner, workers: int) -> str | bytes | EgoPlanner:
    """What the workers get: a spec as is, an object pickled (TypeError naming
    ``planner`` when it cannot be, with what to do instead)."""
    if isinstance(planner, str) or workers <= 1:
        return planner
    try:
        return pickle.dumps(planner)
    except (pickle.PicklingError, TypeError, AttributeError) as err:
        raise TypeError(
            f"planner {planner!r} cannot be sent to worker processes ({err}); give it as a "
            "spec ('package.module:object' or 'file.py:object') or run with workers=1"
        ) from err


def run_jobs(
    planner: str | EgoPlanner,
    setup: EpisodeSetup,
    scenes: Scenes,
    seeds: Sequence[int],
    workers: int = 1,
    progress: bool = True,
    on_episode: Callable[[Episode], None] | None = None,
) -> list[Episode]:
    """Every (scene, seed) episode, in job order; ``on_episode`` sees each as it returns."""
    jobs = [(index, seed) for index in range(scenes.count) for seed in seeds]
    worker = _Worker(portable_planner(planner, workers), setup, scenes)
    bar = tqdm(total=len(jobs), desc="episodes", unit="episode", disable=not progress)
    done: list[Episode] = []
    failed, interrupted, error = 0, False, None
    try:
        for episode in _episodes(worker, jobs, workers):
            done.append(episode)
            failed += bool(episode.analysed.failures)
            if on_episode is not None:
                on_episode(episode)
            bar.set_postfix_str(f"ego collisions {failed}", refresh=False)
            bar.update()
    except (KeyboardInterrupt, SystemError) as stop:  # SystemError: Ctrl-C inside numba
        if interrupt_of(stop) is None:
            raise
        interrupted = True
    except PlannerError as raised:
        error = raised
    finally:
        bar.close()
        if worker.runner is not None:
            worker.runner.close()
    order = {job: position for position, job in enumerate(jobs)}
    done.sort(key=lambda e: order[(e.index, e.seed)])
    if interrupted:
        raise StressInterrupted(done, len(jobs))
    if error is not None:
        raise PlannerFailed(str(error), done, len(jobs)) from error
    return done


class PlannerFailed(PlannerError):
    """A :class:`PlannerError` during :func:`run_jobs`, with the ``episodes`` that finished
    before it, in job order, of ``planned``."""

    def __init__(self, message: str, episodes: list[Episode], planned: int) -> None:
        super().__init__(message)
        self.episodes, self.planned = episodes, planned

    def __reduce__(self) -> tuple:  # picklable, e.g. out of a user's worker process
        return type(self), (self.args[0], self.episodes, self.planned)


class StressInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`run_jobs`: ``episodes`` are those that finished, in job order,
    of ``planned``."""

    def __init__(self, episodes: list[Episode], planned: int) -> None:
        super().__init__(f"{len(episodes)} of {planned} episodes finished")
        self.episodes, self.planned = episodes, planned

    def __reduce__(self) -> tuple:
        return type(self), (self.episodes, self.planned)


def _episodes(worker: _Worker, jobs: list[tuple[int, int]], workers: int) -> Iterator[Episode]:
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            yield worker(job)
        return
    context = multiprocessing.get_context("spawn")
    with context.Pool(min(workers, len(jobs)), _init_worker, (worker,)) as pool:
        yield from pool.imap_unordered(_run_job, jobs, chunksize=1)


__all__ = [
    "Episode",
    "GuardedPlanner",
    "PlannerError",
    "PlannerFailed",
    "SceneSourceError",
    "Scenes",
    "StressInterrupted",
    "StressOptions",
    "portable_planner",
    "resolve_planner",
    "run_jobs",
]
