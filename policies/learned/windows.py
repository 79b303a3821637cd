"""Training windows: one scene at one current step, in the ego's frame (docs/how-to/windows.md).

:func:`build_window` is the one function that turns agent tracks into the
:class:`~policies.learned.window_types.Window` of the RiskFlow model. Two entry points share it:

* :func:`window_from_scenario` — a recorded scene at any current step, with the
  reference future and the actions that drive it (training data);
* :func:`window_from_view` — the env's live :class:`~riskflow_env.view.SceneView`,
  without the future fields (the closed-loop policy, every planning cycle).

Both choose agents with :func:`riskflow_env.simulator.select_agents` (the ego first, then
the others valid at the current step, nearest first), keep those within
``WindowConfig.max_distance`` of the ego, and give them window slots in that order.

Recorded speeds and headings may disagree with recorded positions (real data). Windows
keep the recorded states as given; ``actions`` come from :func:`riskflow_env.dynamics.inverse`
over speeds and headings only, so rolling them out from the current state reproduces the
future speeds and headings exactly and the future positions only as far as the track
follows the unicycle model. The training loss compares positions, so such inconsistency
shows up there (as irreducible error), not as silently altered data.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from numbers import Integral
from typing import TYPE_CHECKING

import numpy as np

from policies.dataclass_cli import check_at_least, check_field_types
from policies.learned.window_types import Window, WindowBatch, collate_windows
from riskflow_env import dynamics
from riskflow_env.config import DynamicsConfig, is_number, plain_number
from riskflow_env.dynamics import SPEED, YAW
from riskflow_env.geometry import to_frame
from riskflow_env.maps import DrivableMap
from riskflow_env.risk import MAX_INTERACTION_DISTANCE, pairwise_features
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.simulator import select_agents
from riskflow_env.view import SceneView

if TYPE_CHECKING:
    import torch

CROP_LAYERS = ("drivable", "sdf")


@dataclass(frozen=True)
class WindowConfig:
    """How windows are cut from a scene.

    Attributes:
        history_steps: states per agent up to and including the current one [steps].
        future_steps: reference future states after the current one [steps].
        crop_size: side of the agent-centred map crops [px].
        crop_resolution: crop pixel size [m/px].
        sdf_clip: the SDF crop layer is clipped to ``[-sdf_clip, sdf_clip]`` [m].
        max_agents: window slots at most, the ego included.
        max_distance: agents farther than this from the ego at the current step are left
            out [m]; 150 m is beyond what a vehicle closing at 30 m/s covers in the 5.2 s plan.
        interaction_distance: pairs farther apart than this are masked in ``pair_mask`` [m].
        clip_actions: clip the inverse-dynamics actions to the dynamics bounds; off by
            default (actions as measured; check ``dynamics`` bounds where that matters).
        dynamics: time step [s] (must match the scene's) and bounds.
    """

    history_steps: int = 31
    future_steps: int = 52
    crop_size: int = 48
    crop_resolution: float = 1.0
    sdf_clip: float = 10.0
    max_agents: int = 32
    max_distance: float = 150.0
    interaction_distance: float = MAX_INTERACTION_DISTANCE
    clip_actions: bool = False
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)

    def __post_init__(self) -> None:
        check_field_types(self, "WindowConfig")
        counts = ("history_steps", "future_steps", "crop_size", "max_agents")
        check_at_least(self, dict.fromkeys(counts, 1), owner="WindowConfig")
        for name in ("crop_resolution", "sdf_clip", "max_distance", "interaction_distance"):
            value = getattr(self, name)  # numpy scalars too, stored as Python numbers; no bools
            if not is_number(value) or math.isnan(value) or value <= 0:
                raise ValueError(f"WindowConfig.{name} must be a number > 0, got {value!r}")
            object.__setattr__(self, name, plain_number(value))


def build_window(
    tracks: np.ndarray,
    valid: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    drivable_map: DrivableMap,
    rows: np.ndarray,
    current_index: int,
    config: WindowConfig,
    with_future: bool = True,
) -> Window:
    """The :class:`Window` of docs/how-to/windows.md for the agents ``rows`` at ``current_index``.

    Steps outside ``[0, T)`` are invalid; invalid states and actions are 0.

    Args:
        tracks: (N, T, 4) world-frame states (x [m], y [m], v [m/s], psi [rad]).
        valid: (N, T) bool, observed states.
        length: (N,) vehicle lengths [m].
        width: (N,) vehicle widths [m].
        drivable_map: the scene's map (world frame).
        rows: (A,) int rows of ``tracks`` to put in the window, ego first; each must be
            valid at ``current_index``.
        current_index: index of the current step in ``tracks``' time axis.
        config: window sizes and options.
        with_future: set ``future``, ``future_valid``, ``actions``, ``actions_valid``.

    Returns:
        the window (numpy arrays; ``agent_index`` (A,) int64 = ``rows``). Positions and
        headings are in the scene frame (ego pose at the current step); headings are
        wrapped to (-pi, pi].
    """
    rows = np.asarray(rows, dtype=np.int64)
    num_steps = tracks.shape[1]
    if rows.ndim != 1 or rows.size == 0:
        raise ValueError(f"rows must be a non-empty (A,) index array, got shape {rows.shape}")
    if not 0 <= current_index < num_steps:
        raise ValueError(f"current_index must be in [0, {num_steps}), got {current_index}")
    if not np.all(valid[rows, current_index]):
        raise ValueError("build_window: every selected agent must be valid at current_index")
    history_steps, future_steps = config.history_steps, config.future_steps
    span = history_steps + (future_steps if with_future else 0)
    times = current_index - history_steps + 1 + np.arange(span)  # (S,)
    inside = (times >= 0) & (times < num_steps)
    times_clipped = np.clip(times, 0, num_steps - 1)
    seq_valid = valid[rows[:, None], times_clipped[None, :]] & inside  # (A, S)
    world = np.where(seq_valid[..., None], tracks[rows[:, None], times_clipped[None, :]], 0.0)

    ego_pose = tracks[rows[0], current_index]
    cos, sin = math.cos(ego_pose[YAW]), math.sin(ego_pose[YAW])
    dx, dy = world[..., 0] - ego_pose[0], world[..., 1] - ego_pose[1]
    scene = np.stack(
        [
            *to_frame(dx, dy, cos, sin),
            world[..., SPEED],
            dynamics.wrap_angle(world[..., YAW] - ego_pose[YAW]),
        ],
        axis=-1,
    )
    scene = np.where(seq_valid[..., None], scene, 0.0)  # (A, S, 4)
    current = scene[:, history_steps - 1]  # (A, 4)
    agent_mask = np.ones(rows.size, dtype=bool)
    lengths, widths = length[rows].astype(np.float64), width[rows].astype(np.float64)

    # float32 queries: ~1.6x faster lookups, errors ~1e-5 m at 1 km from the origin.
    now_world = tracks[rows, current_index].astype(np.float32)
    crops = [
        drivable_map.crop(
            now_world[:, :2], now_world[:, YAW], config.crop_size, config.crop_resolution, layer
        )
        for layer in CROP_LAYERS
    ]
    crops[1] = np.clip(crops[1], -config.sdf_clip, config.sdf_clip)
    pair_features, pair_mask = pairwise_features(
        current, lengths, widths, agent_mask, max_distance=config.interaction_distance
    )
    future = {}
    if with_future:
        chain = scene[:, history_steps - 1 :]  # (A, F + 1, 4): current, then the future
        chain_valid = seq_valid[:, history_steps - 1 :]
        actions_valid = chain_valid[:, :-1] & chain_valid[:, 1:]
        actions = dynamics.inverse(chain, config.dynamics, clip=config.clip_actions)
        future = {
            "future": scene[:, history_steps:].astype(np.float32),
            "future_valid": seq_valid[:, history_steps:],
            "actions": np.where(actions_valid[..., None], actions, 0.0).astype(np.float32),
            "actions_valid": actions_valid,
        }
    return Window(
        history=scene[:, :history_steps].astype(np.float32),
        history_valid=seq_valid[:, :history_steps],
        agent_mask=agent_mask,
        agent_index=rows,
        length=lengths.astype(np.float32),
        width=widths.astype(np.float32),
        map_crops=np.stack(crops, axis=1).astype(np.float32),
        pair_features=pair_features.astype(np.float32),
        pair_mask=pair_mask,
        **future,
    )


def scene_to_world(states: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """World states of scene-frame ``states`` (..., 4); ``frame`` = (x, y, yaw), the world
    pose of the scene frame (the ego's at the window's current step). Float64; headings
    are shifted by the frame's yaw, not wrapped. The inverse of :func:`build_window`'s
    frame change."""
    cos, sin = math.cos(frame[2]), math.sin(frame[2])
    x, y = states[..., 0].astype(np.float64), states[..., 1].astype(np.float64)
    return np.stack(
        [
            frame[0] + cos * x - sin * y,
            frame[1] + sin * x + cos * y,
            states[..., SPEED].astype(np.float64),
            states[..., YAW] + frame[2],
        ],
        axis=-1,
    )


def select_rows(scenario: Scenario, current_index: int, config: WindowConfig) -> np.ndarray:
    """Rows of ``scenario`` that get window slots at ``current_index``.

    :func:`riskflow_env.simulator.select_agents` on the scene re-indexed so that
    ``current_index`` is its current step, then cut to ``config.max_distance``.

    Returns:
        (A,) int64 rows, ego first, others nearest first.
    """
    if scenario.current_index != current_index:
        scenario = dataclasses.replace(scenario, history_steps=current_index + 1)
    rows = select_agents(scenario, config.max_agents)
    xy = scenario.states[rows, current_index, :2]
    distance = np.linalg.norm(xy - xy[0], axis=-1)
    return rows[distance <= config.max_distance].astype(np.int64)


def _config(config: object) -> WindowConfig:
    """``config``, or the default for None; a TypeError for anything else (a dict of
    options goes through ``WindowConfig(**options)``)."""
    if config is None:
        return WindowConfig()
    if not isinstance(config, WindowConfig):
        raise TypeError(
            f"config must be a WindowConfig or None, got {type(config).__name__} "
            "(options as a dict: WindowConfig(**options))"
        )
    return config


def _check_dt(dt: float, config: WindowConfig, what: str) -> None:
    if not math.isclose(dt, config.dynamics.dt, rel_tol=1e-9):
        raise ValueError(
            f"{what} has dt = {dt} s but WindowConfig.dynamics.dt = {config.dynamics.dt} s"
        )


def window_from_scenario(
    scenario: Scenario, current_index: int | None = None, config: WindowConfig | None = None
) -> Window:
    """Window of a recorded scene at ``current_index``, with the reference future.

    Args:
        scenario: the scene; its ego must be valid at ``current_index``.
        current_index: index into ``scenario.states``' time axis; default the scenario's
            own current step.
        config: window options; default :class:`WindowConfig`.

    Returns:
        the window (docs/how-to/windows.md) with the future fields; ``agent_index`` holds
        scenario rows.
    """
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be a Scenario, got {type(scenario).__name__}")
    config = _config(config)
    _check_dt(scenario.dt, config, "scenario")
    if current_index is None:
        current_index = scenario.current_index
    if isinstance(current_index, (bool, np.bool_)) or not isinstance(current_index, Integral):
        raise ValueError(f"current_index must be an int step index, got {current_index!r}")
    if not 0 <= current_index < scenario.states.shape[1]:
        raise ValueError(
            f"current_index must be in [0, {scenario.states.shape[1]}), got {current_index}"
        )
    if not scenario.valid[scenario.ego_index, current_index]:
        raise ValueError(f"the ego is not valid at current_index {current_index}")
    rows = select_rows(scenario, current_index, config)
    return build_window(
        scenario.states,
        scenario.valid,
        scenario.length,
        scenario.width,
        scenario.map,
        rows,
        current_index,
        config,
        with_future=True,
    )


def window_from_view(view: SceneView, config: WindowConfig | None = None) -> Window:
    """Window of the live scene, without the future fields (closed-loop planning).

    Every vehicle present in the view takes part (done vehicles too: they stay on the map
    as obstacles); ``agent_index`` holds env slots, so ``view.agent_names[i]`` names
    window slot ``k`` with ``i = window.agent_index[k]``.

    Args:
        view: the env's read-only scene view.
        config: window options; default :class:`WindowConfig`.
    """
    config = _config(config)
    _check_dt(view.dt, config, "view")
    valid = view.history_valid & view.present[:, None]
    # The view as a scene whose current step is its last one, so agents are chosen by the
    # same rule as in recorded scenes (select_agents).
    live_scene = Scenario(
        map=view.map,
        states=view.history,
        valid=valid,
        length=view.length,
        width=view.width,
        ego_index=0,
        dt=view.dt,
        history_steps=view.history.shape[1],
    )
    rows = select_rows(live_scene, live_scene.current_index, config)
    return build_window(
        view.history,
        valid,
        view.length,
        view.width,
        view.map,
        rows,
        live_scene.current_index,
        config,
        with_future=False,
    )


def cut_windows(
    views: Sequence[SceneView], config: WindowConfig, device: torch.device | str = "cpu"
) -> tuple[list[Window], WindowBatch]:
    """The window of each of B scenes (:func:`window_from_view`, numpy, scene by scene) and
    their collated batch (agents padded to the largest scene and masked) on ``device``."""
    windows = [window_from_view(view, config) for view in views]
    return windows, collate_windows(windows).to(device)
