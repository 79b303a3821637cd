"""``riskflow_stress(planner, ...)``: the stress test as one call, and its output folder.

::

    from policies.stress import riskflow_stress

    result = riskflow_stress("idm", scenes=20, seeds=(0, 1, 2), out="outputs/stress")
    print(result.headline)

The output folder (``out``; None writes nothing):

=====================  ====================================================================
``episodes.jsonl``     one row per episode, appended as each returns (a run that dies keeps
                       every finished episode)
``failures/*.npz``     a replay file per failed episode (:mod:`policies.stress.replay`),
                       written as it returns
``summary.json``       :func:`~policies.stress.summary.stress_summary`'s dict, the time to
                       collision, ``planner``, ``options`` and ``per_episode`` (the rows of
                       ``episodes.jsonl`` in job order); written atomically when the
                       episodes are done, and again with the GIFs
``report.md``,         the report (:mod:`policies.stress.report`), written with it; the HTML
``report.html``        page embeds the GIFs
``gifs/*.gif``         the ``gifs`` worst failures (avoidable first, then by impact speed),
                       re-run with the attacker marked and the witness drawn
=====================  ====================================================================

A run replaces these files of a previous run in the same folder (and nothing else there).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from policies.harness import mean_summary, summarize
from policies.planners import EgoPlanner
from policies.stress.planner_spec import spec_of
from policies.stress.replay import rerun, save_replay
from policies.stress.report import write_reports
from policies.stress.runner import (
    Episode,
    GuardedPlanner,
    PlannerError,
    PlannerFailed,
    Scenes,
    StressInterrupted,
    StressOptions,
    resolve_planner,
    run_jobs,
)
from policies.stress.summary import (
    attacked_steps,
    counted,
    headline,
    slow_ego_steps,
    stress_summary,
)
from riskflow_env.atomic_files import write_text
from riskflow_env.cli_errors import interrupt_of
from riskflow_env.config import is_integer
from riskflow_env.folder_lock import make_output_folder
from riskflow_env.scenarios import Scenario


@dataclass(frozen=True)
class StressResult:
    """A finished stress test.

    Attributes:
        summary: what ``summary.json`` holds (module docstring).
        episodes: every episode, in job order (scenes outer, seeds inner).
        out: the output folder (None: nothing written).
    """

    summary: dict[str, Any]
    episodes: tuple[Episode, ...]
    out: Path | None

    @property
    def headline(self) -> str:
        """One line: the avoidable-failure rate with its interval and the counter-metrics."""
        return headline(self.summary)

    @property
    def replays(self) -> list[Path]:
        """The replay files written, in job order."""
        return [e.replay for e in self.episodes if e.replay is not None]


def riskflow_stress(
    planner: str | EgoPlanner,
    scenes: int | Sequence[Scenario] = 20,
    seeds: Sequence[int] = (0,),
    *,
    data: str | os.PathLike | None = None,
    k: int | str = 5,
    target: str = "ego",
    planning_interval: float = 0.5,
    steps: int = 100,
    device: str = "cpu",
    checkpoint: str | os.PathLike | None = None,
    workers: int = 1,
    out: str | os.PathLike | None = None,
    gifs: int = 3,
    progress: bool = True,
) -> StressResult:
    """Stress-test ``planner`` against the RiskFlow adversary (``riskflow-stress``).

    Args:
        planner: an ``EgoPlanner`` object, or a spec (``"idm"``, ``"pkg.mod:object"``,
            ``"file.py:object"``: :func:`~policies.stress.planner_spec.load_planner`).
            With ``workers > 1`` an object must pickle; a spec is loaded in each worker.
        scenes: the first N scenes of ``data``, or the scenarios themselves.
        seeds: adversary noise seeds (or one seed); each scene runs once per seed.
        data: a folder of ``.npz`` scenes or a ScenarioNet dataset; None: the shipped
            evaluation bank.
        k, target, planning_interval, steps, device, checkpoint: the adversary and the
            episode (:class:`~policies.stress.episode.EpisodeSetup`).
        workers: processes; the results do not depend on it.
        out: output folder (module docstring); None writes nothing and draws no GIF.
        gifs: worst failures drawn as GIFs (with ``out``).
        progress: show a progress bar with ETA.

    Returns:
        The :class:`StressResult`.
    """
    options = StressOptions(
        k=str(k), target=target, planning_interval=planning_interval, steps=steps,
        device=device, checkpoint=checkpoint,
        scenes=scenes if isinstance(scenes, (int, np.integer)) else max(len(scenes), 1),
        data=data, seeds=(seeds,) if isinstance(seeds, (int, np.integer)) else tuple(seeds),
        workers=workers,
        out=Path("outputs/stress") if out is None else out, gifs=gifs, progress=progress,
    )  # fmt: skip
    setup = options.setup()
    setup.check_checkpoint()  # before any worker or progress bar
    source = Scenes.of(options.scenes if is_integer(scenes) else scenes, options.data)
    label = spec_of(planner) or _name(planner)
    local = resolve_planner(planner, setup)  # a bad spec fails here, before any worker
    folder = None if out is None else options.out
    writer = _Writer(folder, setup, label, source)
    try:
        episodes, stopped = run_jobs(
            planner if isinstance(planner, str) and workers > 1 else local,
            setup, source, options.seeds, workers, progress, writer.episode_done,
        ), None  # fmt: skip
    except (StressInterrupted, PlannerFailed) as stop:  # report the episodes that finished
        if not stop.episodes or folder is None:
            raise
        episodes, stopped = stop.episodes, stop
    episodes = [
        Episode(e.index, e.seed, e.analysed, writer.replays.get((e.index, e.seed)))
        for e in episodes
    ]
    summary = summary_of(episodes)
    summary |= {
        "planner": label,
        "options": {
            **{key: value for key, value in options.setup().as_json().items()},
            "scenes": source.count, "data": None if data is None else str(data),
            "seeds": list(options.seeds), "workers": workers,
        },
        "per_episode": [writer.row(e) for e in episodes],
    }  # fmt: skip
    if stopped is not None:
        cause = "the planner raised" if isinstance(stopped, PlannerFailed) else "interrupted"
        summary["interrupted"] = {
            "episodes": len(episodes),
            "planned": stopped.planned,
            "cause": cause,
        }
    if folder is not None:
        writer.report(summary, [])  # first without GIFs: Ctrl-C while drawing keeps them
        if stopped is not None:
            kept = f"{folder}/summary.json and the reports cover them (no GIF)"
            if isinstance(stopped, PlannerFailed):
                raise PlannerFailed(
                    f"{stopped}; {len(episodes)} of {stopped.planned} episodes finished "
                    f"before it: {kept}",
                    episodes,
                    stopped.planned,
                ) from stopped.__cause__  # the planner's own traceback under --debug
            raise KeyboardInterrupt(f"{stopped}; {kept}")
        try:
            gif_rows = writer.draw_worst(episodes, local, gifs, progress)
        except PlannerError as error:
            raise PlannerError(
                f"{error}; {folder}/summary.json and the reports cover all "
                f"{counted(len(episodes), 'episode')} (no GIF)"
            ) from error
        except (KeyboardInterrupt, SystemError) as error:  # SystemError: Ctrl-C in numba
            if interrupt_of(error) is None:
                raise
            raise KeyboardInterrupt(
                f"while drawing the GIFs; {folder}/summary.json and the reports cover all "
                f"{counted(len(episodes), 'episode')} (no GIF)"
            ) from None
        if gif_rows:
            writer.report(summary, gif_rows)
    return StressResult(summary, tuple(episodes), folder)


def summary_of(episodes: Sequence[Episode]) -> dict[str, Any]:
    """``stress_summary`` of the episodes, with the time to the first ego collision [s],
    the time from the attack's start to the impact [s] and the ego's off-road rate."""
    analysed = [e.analysed for e in episodes]
    summary = stress_summary(analysed)
    closed_loop = summarize([a.record for a in analysed])
    failures = [f for a in analysed for f in a.failures]
    summary["time_to_first_ego_collision"] = closed_loop["time_to_first_ego_collision"]
    summary["attack_to_impact"] = mean_summary(
        [f.time - f.attack_start for f in failures if f.attack_start is not None]
    )
    summary["ego_offroad_rate"] = closed_loop["ego_offroad_rate"]
    return summary


def severity(episode: Episode) -> tuple:
    """Sort key of failed episodes, worst first: an avoidable failure, then the fastest
    impact, then job order."""
    failures = episode.analysed.failures
    avoidable = any(f.avoidable for f in failures)
    speed = max((f.relative_speed for f in failures), default=0.0)
    return (not avoidable, -speed, episode.index, episode.seed)


class _Writer:
    """Writes a run's files as its episodes return (module docstring)."""

    def __init__(self, folder: Path | None, setup, planner: str, source: Scenes) -> None:
        self.folder, self.setup, self.planner = folder, setup, planner
        self.replays: dict[tuple[int, int], Path] = {}
        names = [s.name for s in source.scenarios]
        self.duplicates = {name for name in names if names.count(name) > 1}
        if folder is None:
            return
        make_output_folder(folder, "--out")
        for old in (
            *folder.glob("failures/*-seed*.npz"), *folder.glob("gifs/*-seed*.gif"),
            *(folder / name for name in ("episodes.jsonl", "summary.json", "report.md",
                                         "report.html")),
        ):  # fmt: skip
            old.unlink(missing_ok=True)
        self.checkpoint_sha256 = setup.checkpoint_sha256()

    def stem(self, episode: Episode) -> str:
        name = episode.analysed.record.scenario.name
        if name in self.duplicates:
            name = f"{episode.index:04d}-{name}"
        return f"{re.sub(r'[^A-Za-z0-9._-]+', '_', name)}-seed{episode.seed}"

    def episode_done(self, episode: Episode) -> None:
        if self.folder is None:
            return
        if episode.analysed.failures:
            path = self.folder / "failures" / f"{self.stem(episode)}.npz"
            path.parent.mkdir(exist_ok=True)
            save_replay(
                path, episode.analysed, episode.seed, self.setup, self.planner,
                self.checkpoint_sha256,
            )  # fmt: skip
            self.replays[(episode.index, episode.seed)] = path
        episode = Episode(
            episode.index, episode.seed, episode.analysed,
            self.replays.get((episode.index, episode.seed)),
        )  # fmt: skip
        with open(self.folder / "episodes.jsonl", "a", encoding="utf-8") as file:
            file.write(json.dumps(self.row(episode)) + "\n")
            file.flush()
            os.fsync(file.fileno())

    def row(self, episode: Episode) -> dict[str, Any]:
        """The JSON row of an episode."""
        record, failures = episode.analysed.record, episode.analysed.failures
        replay = episode.replay
        if replay is not None and self.folder is not None:
            replay = replay.relative_to(self.folder)
        return {
            "index": episode.index,
            "scene": record.scenario.name,
            "family": record.scenario.family or "unknown",
            "seed": episode.seed,
            "ego_collided": bool(failures),
            "avoidable_failure": any(f.avoidable for f in failures),
            "failures": [f.to_dict() for f in failures],
            "replay": None if replay is None else replay.as_posix(),
            "metrics": record.metrics,
            "attacked_steps": attacked_steps(record),
            "slow_ego_steps": slow_ego_steps(record),
        }

    def report(self, summary: dict[str, Any], gif_rows: list[dict[str, Any]]) -> None:
        """``summary.json`` (with ``summary["gifs"]``, set here) and the reports, atomically."""
        summary["gifs"] = [
            {key: row[key] for key in ("scene", "seed", "gif", "reproduced")} for row in gif_rows
        ]
        _write_json(self.folder / "summary.json", summary)
        write_reports(self.folder, summary, gif_rows)

    def draw_worst(
        self, episodes: Sequence[Episode], planner: EgoPlanner, count: int, progress: bool
    ) -> list[dict[str, Any]]:
        """GIFs of the ``count`` worst failed episodes (:func:`severity`), each re-run with
        ``planner`` (a progress bar with ``progress``); the rows the report shows them
        with."""
        failed = sorted((e for e in episodes if e.analysed.failures), key=severity)
        rows = []
        worst = failed[:count]
        shown = progress and bool(worst)  # no empty bar when nothing failed
        bar = tqdm(worst, "drawing GIFs", unit="gif", disable=not shown, leave=False)
        guarded = GuardedPlanner(planner)
        for episode in bar:
            gif = self.folder / "gifs" / f"{self.stem(episode)}.gif"
            failures = [f.to_dict() for f in episode.analysed.failures]
            guarded.where = f"re-running scene {episode.index}, seed {episode.seed} for its GIF"
            again = rerun(
                episode.analysed.record.scenario, episode.seed, self.setup, guarded, gif, failures
            )
            same = np.array_equal(again.record.states, episode.analysed.record.states)
            rows.append({**self.row(episode), "gif": f"gifs/{gif.name}", "reproduced": same})
        return rows


def _name(planner: object) -> str:
    return getattr(planner, "__name__", None) or type(planner).__name__


def _write_json(path: Path, value: Any) -> None:
    """``value`` as JSON at ``path``, atomically."""
    write_text(path, json.dumps(value, indent=2, default=str) + "\n")


__all__ = ["StressResult", "riskflow_stress", "severity", "summary_of"]
