"""Naturalistic scenes: windows cut from highway-env IDM/MOBIL recordings.

A window is ``history_steps + future_steps`` consecutive recorded steps (31 + 100 by
default, 13.1 s at 10 Hz). Its ego is a vehicle valid over the whole window, drawn among
the half of such vehicles with the most neighbours within ``density_radius`` at the
current step (the densest part of the road). The other agents are the vehicles valid at
the current step or entering later, that come within ``radius`` of the ego during the
window (nearest first, at most ``max_agents``); vehicles that leave before the current
step are not kept. Validity masks say when each one is on the map. A window in which a
kept vehicle crashes is rejected.

:func:`generate_scenario` records one simulation and returns its first admissible
window, trying ``candidate_windows`` starts ``window_stride`` steps apart in random order,
and recording again (up to ``max_attempts`` times) when none is admissible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from riskflow_env.config import check_field_types, is_integer
from riskflow_env.scenarios.recording import DriverConfig, Recording, record_traffic
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.state import HISTORY_STEPS

SOURCE = "highway-env-idm"


@dataclass(frozen=True)
class SceneConfig:
    """How recordings are made and cut into scenes.

    Attributes:
        history_steps: history states, the current one included [steps of 0.1 s].
        future_steps: reference future [steps of 0.1 s], >= 1.
        warmup: (min, max) simulated steps before recording starts (drawn per recording).
        candidate_windows: window starts tried per recording.
        window_stride: steps between consecutive window starts.
        radius: keep vehicles that come this close to the ego during the window [m].
        density_radius: neighbourhood counted to rank ego candidates [m].
        ego_top: the ego is drawn among this top share of candidates by density.
        max_agents: most agents per scene, the ego included.
        max_attempts: recordings tried before giving up.
        map_resolution: raster resolution of the maps [m/px].
        driver: ranges of the recorded traffic (density, IDM/MOBIL, sizes).
    """

    history_steps: int = HISTORY_STEPS
    future_steps: int = 100
    warmup: tuple[int, int] = (40, 100)
    candidate_windows: int = 4
    window_stride: int = 10
    radius: float = 80.0
    density_radius: float = 30.0
    ego_top: float = 0.5
    max_agents: int = 48
    max_attempts: int = 5
    map_resolution: float = 0.5
    driver: DriverConfig = field(default_factory=DriverConfig)

    def __post_init__(self) -> None:
        check_field_types(self)
        counts = ("history_steps", "future_steps", "candidate_windows", "max_attempts")
        for name in (*counts, "window_stride", "max_agents"):
            value = getattr(self, name)
            if not is_integer(value) or value < 1:
                raise ValueError(f"SceneConfig.{name} must be an int >= 1, got {value!r}")
            object.__setattr__(self, name, int(value))  # a numpy int as a Python one
        if not 0 <= self.warmup[0] <= self.warmup[1]:
            raise ValueError(f"SceneConfig.warmup must be 0 <= min <= max, got {self.warmup}")
        if not 0 < self.ego_top <= 1:
            raise ValueError(f"SceneConfig.ego_top must be in (0, 1], got {self.ego_top}")
        for name in ("radius", "density_radius", "map_resolution"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SceneConfig.{name} must be > 0 [m], got {getattr(self, name)}")

    @property
    def window_steps(self) -> int:
        """Steps per scene (history + future)."""
        return self.history_steps + self.future_steps


def generate_scenario(
    family: str, rng: np.random.Generator, config: SceneConfig | None = None, name: str = ""
) -> Scenario:
    """One naturalistic scene of ``family``; deterministic given ``rng``'s state.

    Raises:
        RuntimeError: no admissible window in ``config.max_attempts`` recordings.
    """
    cfg = config or SceneConfig()
    steps = cfg.window_steps + (cfg.candidate_windows - 1) * cfg.window_stride
    for _ in range(cfg.max_attempts):
        warmup = int(rng.integers(cfg.warmup[0], cfg.warmup[1] + 1))
        recording = record_traffic(family, rng, steps, warmup, cfg.driver, cfg.map_resolution)
        for window in rng.permutation(cfg.candidate_windows):
            scene = cut_scenario(recording, int(window) * cfg.window_stride, rng, cfg, name)
            if scene is not None:
                return scene
    raise RuntimeError(
        f"generate_scenario: no admissible {family!r} window in {cfg.max_attempts} recordings"
    )


def cut_scenarios(
    recording: Recording, rng: np.random.Generator, config: SceneConfig | None = None
) -> list[Scenario]:
    """Every admissible window of ``recording``, starts ``config.window_stride`` apart."""
    cfg = config or SceneConfig()
    last_start = recording.valid.shape[1] - cfg.window_steps
    scenes = [
        cut_scenario(recording, start, rng, cfg, name=f"{recording.family}-{start}")
        for start in range(0, last_start + 1, cfg.window_stride)
    ]
    return [scene for scene in scenes if scene is not None]


def cut_scenario(
    recording: Recording,
    start: int,
    rng: np.random.Generator,
    config: SceneConfig | None = None,
    name: str = "",
) -> Scenario | None:
    """The scene of the window starting at recorded step ``start``, or None when no
    vehicle is valid over the whole window or a kept vehicle crashes in it.

    States are rounded to float32 precision (about 1e-4 m at 1 km, so scene files store
    them losslessly in half the space); headings are shifted by whole turns so that each
    agent's first valid heading lies in [-pi, pi).
    """
    cfg = config or SceneConfig()
    end, total = start + cfg.window_steps, recording.valid.shape[1]
    if start < 0 or end > total:
        raise ValueError(f"window [{start}, {end}) does not fit the recording's {total} steps")
    valid = recording.valid[:, start:end]
    states = recording.states[:, start:end]
    now = cfg.history_steps - 1
    last = total - 1 - np.argmax(recording.valid[:, ::-1], axis=1)
    crash_inside = recording.crashed & (last >= start) & (last < end - 1)

    candidates = np.flatnonzero(valid.all(axis=1) & ~crash_inside)
    if candidates.size == 0:
        return None
    xy_now = states[:, now, :2]
    present = valid[:, now]
    gaps = np.linalg.norm(xy_now[candidates, None] - xy_now[None, present], axis=-1)
    density = np.sum(gaps < cfg.density_radius, axis=1)
    ranked = candidates[np.argsort(-density, kind="stable")]
    ego = int(rng.choice(ranked[: max(1, math.ceil(cfg.ego_top * ranked.size))]))

    both = valid & valid[ego]
    distance = np.linalg.norm(states[:, :, :2] - states[ego, None, :, :2], axis=-1)
    closest = np.where(both, distance, np.inf).min(axis=1)
    keep = valid[:, now:].any(axis=1) & (closest <= cfg.radius)
    keep[ego] = False
    if np.any(crash_inside & keep):
        return None
    others = np.flatnonzero(keep)
    others = others[np.argsort(closest[others], kind="stable")][: cfg.max_agents - 1]
    rows = np.concatenate([[ego], others]).astype(int)

    tracks = np.where(valid[rows, :, None], states[rows], 0.0)
    first = np.argmax(valid[rows], axis=1)
    first_heading = tracks[np.arange(rows.size), first, 3]
    turns = np.floor((first_heading + np.pi) / (2 * np.pi))
    tracks[:, :, 3] -= np.where(valid[rows], 2 * np.pi * turns[:, None], 0.0)
    tracks = tracks.astype(np.float32).astype(np.float64)
    return Scenario(
        map=recording.map,
        states=tracks,
        valid=valid[rows].copy(),
        length=recording.length[rows].copy(),
        width=recording.width[rows].copy(),
        ego_index=0,
        agent_ids=tuple(f"vehicle_{row}" for row in rows),
        name=name,
        dt=recording.dt,
        history_steps=cfg.history_steps,
        kinds=tuple(recording.kinds[row] for row in rows),
        source=SOURCE,
        family=recording.family,
    )
