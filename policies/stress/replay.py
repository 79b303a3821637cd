"""Replay files: every failure of a stress test, saved so that a planner can face it again.

A replay file (``failures/<scene>-seed<k>.npz``) is a scenario file
(:func:`~riskflow_env.scenarios.save_scenario`, map SDF included, so that it loads bit for
bit; :func:`~riskflow_env.scenarios.load_scenario` and ``examples/rollout.py --scenario``
read it) with three more members (``extra_`` members, which scenario loaders check and
ignore): ``extra_stress`` (UTF-8 JSON: the adversary seed, the
:class:`~policies.stress.episode.EpisodeSetup`, the generator file's hash, the planner
spec, the episode's metrics and its failures with their witness trajectories) and the
executed ``extra_stress_states`` / ``extra_stress_in_scene`` of the failed episode.

**Replay re-runs the episode closed loop**: the scene from its start, the adversary with
the same seed and options (the adversary is deterministic per seed), the planner given now
driving the ego. The other way, replaying the others' recorded trajectories open loop,
would put a fixed planner against vehicles that no longer react to it: an ego that brakes
earlier would be rammed by a trajectory aimed at where it used to be, or an escape would
be credited that the adversary would have closed. Closed loop, the same planner gives the
same episode bit for bit (``identical``), and a fixed planner faces the same adversary,
which is the question a fix must answer.
"""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policies.harness import EpisodeRecord
from policies.planners import EgoPlanner
from policies.stress.episode import EpisodeRunner, EpisodeSetup
from policies.stress.planner_spec import load_planner
from policies.stress.summary import Analysed
from riskflow_env.atomic_files import atomic_path
from riskflow_env.render import RenderConfig
from riskflow_env.scenarios import Scenario, load_scenario, save_scenario

FORMAT = "riskflow-stress-replay"
VERSION = 1
WITNESS_COLOR = (60, 230, 110)  # the escape the search found
ATTACKER_COLOR = (255, 60, 60)
WALL_TIMES = ("planning_time_ms", "planning_time_max_ms", "ego_time_ms")  # not saved: they vary
GIF_VIEW = RenderConfig(width_px=480, height_px=300, view_width=70.0)


@dataclass(frozen=True)
class Replay:
    """A replay file, read back: the starting scenario, the seed, the setup, the metadata
    (``stress`` JSON) and the executed states of the failed episode."""

    path: Path
    scenario: Scenario
    seed: int
    setup: EpisodeSetup
    meta: dict[str, Any]
    states: np.ndarray
    in_scene: np.ndarray


@dataclass(frozen=True)
class ReplayResult:
    """What a replay found.

    Attributes:
        replay: the file replayed.
        analysed: the new episode and its failures.
        recurred: the ego collided again.
        identical: the new episode is the saved one, bit for bit (states, flags, events).
        checkpoint_matches: the generator file is the one the failure was found with.
    """

    replay: Replay
    analysed: Analysed
    recurred: bool
    identical: bool
    checkpoint_matches: bool

    def describe(self) -> str:
        """A few lines: the saved failure, what happened now."""
        saved = self.replay.meta["failures"]
        lines = [f"{self.replay.path}: scene {self.replay.scenario.name}, seed {self.replay.seed}"]
        lines += [f"  saved failure: {describe_failure(row)}" for row in saved]
        now = [f.to_dict() for f in self.analysed.failures]
        lines += [f"  now:           {describe_failure(row)}" for row in now]
        if not now:
            steps = self.analysed.record.metrics["steps"]
            lines.append(f"  now:           no ego collision in {steps} steps")
        verdict = "RECURS" if self.recurred else "does NOT recur"
        same = "identical to the saved episode, bit for bit" if self.identical else "a new episode"
        lines.append(f"  the failure {verdict} ({same})")
        if not self.checkpoint_matches:
            lines.append("  warning: the generator checkpoint differs from the one saved")
        return "\n".join(lines)


def describe_failure(row: dict[str, Any]) -> str:
    """One line of a failure's ``to_dict()``."""
    verdict = "avoidable" if row["avoidable"] else "not shown avoidable"
    return (
        f"{row['type']} by {row['attacker']} at {row['time']:.1f} s, "
        f"{row['relative_speed']:.1f} m/s, ego {row['ego_speed']:.1f} m/s, {verdict}"
    )


def save_replay(
    path: str | os.PathLike,
    analysed: Analysed,
    seed: int,
    setup: EpisodeSetup,
    planner: str,
    checkpoint_sha256: str | None = None,
) -> Path:
    """Write the replay file of a failed episode (module docstring) atomically."""
    path = Path(path)
    record = analysed.record
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "scene": record.scenario.name,
        "seed": int(seed),
        "setup": setup.as_json(),
        "checkpoint_sha256": checkpoint_sha256 or setup.checkpoint_sha256(),
        "planner": planner,
        "metrics": {k: v for k, v in record.metrics.items() if k not in WALL_TIMES},
        "events": event_rows(record),
        "failures": [failure.to_dict() for failure in analysed.failures],
    }
    with atomic_path(path, suffix=".tmp.npz") as temporary:
        save_scenario(record.scenario, temporary, include_sdf=True)
        extra = {
            # UTF-8 bytes, not a str array: scenario files cap their strings at 1,024 chars
            "extra_stress": np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
            "extra_stress_states": record.states,
            "extra_stress_in_scene": record.in_scene,
        }
        with zipfile.ZipFile(temporary, "a", compression=zipfile.ZIP_DEFLATED) as archive:
            for key, value in extra.items():
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                with archive.open(info, "w", force_zip64=True) as handle:
                    np.lib.format.write_array(handle, value, allow_pickle=False)
    return path


def event_rows(record: EpisodeRecord) -> list[dict[str, Any]]:
    """The episode's event rows without the ``episode`` counter (which counts a loop's
    episodes, not this episode's content)."""
    return [{k: v for k, v in event.items() if k != "episode"} for event in record.events]


def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value))


def load_replay(path: str | os.PathLike) -> Replay:
    """Read a replay file; FileNotFoundError or IsADirectoryError when there is no file at
    ``path``, ValueError naming the file when it is not a replay file."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{str(path)!r} is a folder, not a replay file (failures/*.npz)")
    if not path.is_file():
        raise FileNotFoundError(f"replay file {str(path)!r} not found")
    scenario = load_scenario(path)
    with np.load(path, allow_pickle=False) as data:
        if "extra_stress" not in data.files:
            raise ValueError(
                f"{path} is a scenario file without a stress-test failure (no 'extra_stress' "
                "member): replay files are the failures/*.npz of a riskflow-stress run"
            )
        meta = json.loads(data["extra_stress"].tobytes().decode())
        states, in_scene = data["extra_stress_states"], data["extra_stress_in_scene"]
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ValueError(
            f"{path}: format {meta.get('format')!r} version {meta.get('version')!r}, "
            f"expected {FORMAT!r} version {VERSION}"
        )
    setup = EpisodeSetup.from_json(meta["setup"])
    return Replay(path, scenario, int(meta["seed"]), setup, meta, states, in_scene)


def replay(
    path: str | os.PathLike | Replay,
    planner: EgoPlanner | str,
    video: str | os.PathLike | None = None,
) -> ReplayResult:
    """Put ``planner`` back into the situation of a replay file (module docstring).

    Args:
        path: the replay file (or a :class:`Replay` read already).
        planner: the planner to test: the one that failed, or a fixed version of it (an
            object, or a spec as :func:`riskflow_stress` takes: ``"idm"``, ``"file.py:obj"``).
        video: a ``.gif`` / ``.mp4`` of the new episode, the saved attacker marked and the
            saved escape (witness) drawn; None: no video.
    """
    saved = path if isinstance(path, Replay) else load_replay(path)
    if isinstance(planner, str):  # a spec, as riskflow_stress takes
        planner = load_planner(planner, saved.setup.env_config().dynamics, argument="planner")
    failures = saved.meta["failures"]
    analysed = rerun(saved.scenario, saved.seed, saved.setup, planner, video, failures)
    record = analysed.record
    identical = (
        np.array_equal(record.states, saved.states)
        and np.array_equal(record.in_scene, saved.in_scene)
        and _jsonable(event_rows(record)) == saved.meta["events"]
        and _jsonable([f.to_dict() for f in analysed.failures]) == failures
    )
    return ReplayResult(
        replay=saved,
        analysed=analysed,
        recurred=bool(analysed.failures),
        identical=identical,
        checkpoint_matches=saved.setup.checkpoint_sha256() == saved.meta["checkpoint_sha256"],
    )


def rerun(
    scenario: Scenario,
    seed: int,
    setup: EpisodeSetup,
    planner: EgoPlanner,
    video: str | os.PathLike | None = None,
    failures: Sequence[dict[str, Any]] = (),
) -> Analysed:
    """The episode of (``scenario``, ``seed``, ``setup``) with ``planner``, recorded to
    ``video`` with the attackers of ``failures`` (``to_dict()`` rows) marked and their
    witnesses drawn."""

    def marked(adversary: Any) -> MarkedPolicy:
        return MarkedPolicy(adversary, failures)

    with EpisodeRunner(
        planner, setup, policy=marked if video is not None else None, video=video,
        render_config=GIF_VIEW,
    ) as runner:  # fmt: skip
        return runner(scenario, seed)


class MarkedPolicy:
    """A scene policy that acts as ``policy`` and, on a video, also draws the attackers
    of ``failures`` (their recent track red, haloed) and the escapes the search found
    (green)."""

    def __init__(self, policy: Any, failures: Sequence[dict[str, Any]]) -> None:
        self.policy, self.failures = policy, list(failures)
        self.view: Any = None

    def reset(self, view: Any) -> None:
        self.policy.reset(view)

    def act(self, view: Any) -> dict[str, np.ndarray]:
        self.view = view
        return self.policy.act(view)

    def __getattr__(self, name: str) -> Any:  # controllable, cycles, ... of the policy
        return getattr(self.policy, name)

    def draw(self, renderer: Any) -> None:
        """The policy's own overlays, then the attackers and the witnesses."""
        draw = getattr(self.policy, "draw", None)
        if callable(draw):
            draw(renderer)
        view = self.view
        for number, row in enumerate(self.failures):
            if row.get("witness"):
                witness = np.asarray(row["witness"])[None, :, :2]
                renderer.set_overlay(
                    f"witness_{number}", witness, color=WITNESS_COLOR, width=3,
                    label=f"escape from {row['reaction_time']:.1f} s (witness)",
                )  # fmt: skip
            if view is None or row["attacker"] not in view.agent_names:
                continue
            mask = np.zeros(view.history_valid.shape, bool)
            slot = view.slot(row["attacker"])
            mask[slot] = view.history_valid[slot]
            renderer.set_overlay(
                f"attacker_{number}", view.history[..., :2], mask=mask, color=ATTACKER_COLOR,
                highlight=(slot,), label=f"attacker {row['attacker']} ({row['type']})",
            )  # fmt: skip


__all__ = [
    "MarkedPolicy",
    "Replay",
    "ReplayResult",
    "describe_failure",
    "event_rows",
    "load_replay",
    "rerun",
    "replay",
    "save_replay",
]
