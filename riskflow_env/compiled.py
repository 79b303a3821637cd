"""The compiled simulator step: numba kernels for numpy float64 scenes.

:func:`riskflow_env.simulator.advance` and :func:`riskflow_env.simulator.evaluate` hand
numpy float64 states to this module when numba is installed (``pip install
riskflow-env[fast]``): the dynamics, and the risk features, the SDF lookups of the
footprints and observation rays, the collision and off-road tests, the observations and
the rewards of a whole batch, run as two compiled loops over scenes, agents and pairs
(:mod:`riskflow_env.compiled_kernels`) instead of a few hundred numpy calls on small
arrays. The array-API functions stay the reference, and the path of torch tensors,
float32 arrays and custom map lookups. The kernels repeat the reference's
floating-point operations in its order, so both paths agree to float rounding (bit for
bit where the C library's ``sin`` and ``cos`` are numpy's, as on the x86-64 Linux VM of
docs/explanation/speed.md).

Switch: the environment variable ``RISKFLOW_COMPILED=0`` turns the compiled path off
(read at every step); without numba the reference runs. The first step of a process
imports numba and loads the kernels from numba's on-disk cache (about 0.25 s); the first
run on a machine, or after the kernels change, compiles them (about 7 s).
"""

from __future__ import annotations

import functools
import math
import os
import weakref
from types import ModuleType
from typing import Any

import numpy as np

from riskflow_env.config import DynamicsConfig, EnvConfig
from riskflow_env.events import FrameEvents
from riskflow_env.kernel_loading import SWITCH, import_kernels
from riskflow_env.maps import DrivableMap, MapStack
from riskflow_env.observations import _sample_offsets
from riskflow_env.rewards import REWARD_TERMS
from riskflow_env.risk import MAX_INTERACTION_DISTANCE, TAU_MAX


@functools.cache
def kernels() -> ModuleType | None:
    """The kernel module, or None where numba cannot be imported or finds no writable
    cache directory (the package's ``__pycache__``, the user's cache, ``NUMBA_CACHE_DIR``;
    a warning says so, and the reference runs)."""
    return import_kernels("riskflow_env.compiled_kernels", "riskflow_env.compiled")


def enabled() -> bool:
    """The compiled path runs: numba is importable and ``RISKFLOW_COMPILED`` is not "0"."""
    return os.environ.get(SWITCH, "1") != "0" and kernels() is not None


def _float64(*arrays: Any) -> bool:
    return all(type(a) is np.ndarray and a.dtype == np.float64 for a in arrays)


def accepts_advance(current: Any, present: Any, active: Any, actions: Any) -> bool:
    """:func:`advance` applies: numpy float64 states and actions, bool masks, of matching
    shapes."""
    return (
        _float64(current, actions)
        and tuple(actions.shape) == (*current.shape[:-1], 2)
        and type(present) is np.ndarray
        and type(active) is np.ndarray
        and present.dtype == active.dtype == np.bool_
        and present.shape == active.shape == current.shape[:-1]
        and enabled()
    )


def advance(
    current: np.ndarray,
    present: np.ndarray,
    active: np.ndarray,
    actions: np.ndarray,
    config: DynamicsConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`riskflow_env.simulator.advance`, compiled (same arguments and returns)."""
    lead = current.shape[:-1]
    new, applied = kernels().advance(
        np.ascontiguousarray(current).reshape(-1, 4),
        present.reshape(-1),
        active.reshape(-1),
        np.ascontiguousarray(actions).reshape(-1, 2),
        _dynamics_params(config),
    )
    return new.reshape(*lead, 4), applied.reshape(*lead, 2)


def accepts_evaluate(state: Any, lookup: Any) -> bool:
    """:func:`evaluate` applies: numpy float64 arrays and a :class:`DrivableMap` (or a
    :class:`MapStack` selection with a map per scene of a batch); a subclass of
    :class:`DrivableMap` may look up its SDF otherwise, so it takes the reference."""
    current = state.current
    if not (
        _float64(current, state.length, state.width, state.last_action)
        and type(state.present) is np.ndarray
        and state.present.dtype == np.bool_
    ):
        return False
    if isinstance(lookup, MapStack.Selection):
        index = lookup.index
        if type(index) is not np.ndarray or current.ndim < 3 or len(index) != len(current):
            return False
    elif type(lookup) is not DrivableMap:
        return False
    return enabled()


def evaluate(state: Any, lookup: Any, config: EnvConfig, observations: bool) -> tuple:
    """:func:`riskflow_env.simulator.evaluate`, compiled: the fields of its
    ``Evaluation`` but the pair features (pair mask, events, observations, reward terms,
    reward), leading dims as ``state``'s. The kernel keeps each scene's pair features
    only while it builds that scene's observations: writing every pair of a large batch
    to memory, which no caller of the env reads, would cost more than the rest."""
    current = state.current
    lead, agents = current.shape[:-2], current.shape[-2]
    scenes = math.prod(lead)
    flat, grid_int, grid_float, scene_map = _map_tables(lookup, lead, scenes)
    out = kernels().evaluate_scenes(
        np.ascontiguousarray(current).reshape(scenes, agents, 4),
        np.ascontiguousarray(state.length).reshape(scenes, agents),
        np.ascontiguousarray(state.width).reshape(scenes, agents),
        np.ascontiguousarray(state.present).reshape(scenes, agents),
        np.ascontiguousarray(state.last_action).reshape(scenes, agents, 2),
        flat,
        grid_int,
        grid_float,
        scene_map,
        _sample_offsets(config.observation),
        _evaluate_params(config),
        config.observation.num_neighbors,
        observations,
    )
    mask, collisions, fraction, depth, centroid, rows, terms, reward = out
    pairs = (*lead, agents, agents)
    events = FrameEvents(
        collisions=collisions.reshape(pairs),
        offroad_fraction=fraction.reshape(*lead, agents),
        sdf_depth=depth.reshape(*lead, agents),
        centroid_offroad=centroid.reshape(*lead, agents),
    )
    per_term = {name: terms[k].reshape(*lead, agents) for k, name in enumerate(REWARD_TERMS)}
    rows = rows.reshape(*lead, agents, rows.shape[-1]) if observations else None
    return mask.reshape(pairs), events, rows, per_term, reward.reshape(*lead, agents)


def _map_tables(lookup: Any, lead: tuple, scenes: int) -> tuple:
    """The SDF rasters end to end, their (height, width, offset) and (origin_x, origin_y,
    resolution, exact 1 / resolution or 0) rows, and the map row of each of the
    ``scenes`` flattened scenes."""
    if isinstance(lookup, DrivableMap):
        return (*_single_map_tables(lookup), np.zeros(scenes, dtype=np.int64))
    flat, grid = lookup._grid(np.zeros((0, 2)))  # (C,) per row of the selection
    flat = flat.view()
    flat.flags.writeable = False  # as a DrivableMap's raster: one compiled signature
    height, width, origin_x, origin_y, resolution, offset = grid
    grid_int = np.stack([height, width, offset], axis=-1).astype(np.int64)
    scale = _exact_inverse(resolution)
    grid_float = np.stack([origin_x, origin_y, resolution, scale], axis=-1).astype(np.float64)
    inner = scenes // len(grid_int)  # scenes within each row (leading dims after the first)
    return flat, grid_int, grid_float, np.repeat(np.arange(len(grid_int)), inner)


_MAP_TABLES: dict[int, tuple] = {}  # id(map) -> (weak reference to it, its tables)


def _single_map_tables(drivable_map: DrivableMap) -> tuple:
    """:func:`_map_tables` of one map but the scene rows, kept while the map lives (a map
    is immutable; rebuilding them cost a tenth of a one-scene step)."""
    entry = _MAP_TABLES.get(id(drivable_map))
    if entry is None or entry[0]() is not drivable_map:
        if len(_MAP_TABLES) >= 64:
            _MAP_TABLES.clear()
        height, width = drivable_map.shape
        origin_x, origin_y = drivable_map._origin
        resolution = drivable_map.resolution
        scale = 1.0 / resolution if math.frexp(resolution)[0] == 0.5 else 0.0
        tables = (
            drivable_map.sdf.reshape(-1),
            np.array([[height, width, 0]], dtype=np.int64),
            np.array([[origin_x, origin_y, resolution, scale]]),
        )
        entry = _MAP_TABLES[id(drivable_map)] = (weakref.ref(drivable_map), tables)
    return entry[1]


def _exact_inverse(resolution: np.ndarray) -> np.ndarray:
    """1 / resolution where resolution is a power of two (multiplying by it then equals
    dividing, bit for bit), else 0."""
    mantissa = np.frexp(resolution)[0]
    return np.where(mantissa == 0.5, 1.0 / resolution, 0.0)


@functools.lru_cache(maxsize=16)
def _dynamics_params(config: DynamicsConfig) -> np.ndarray:
    values = (config.dt, config.accel_min, config.accel_max, config.yaw_rate_max)
    bounds = (config.speed_min, config.speed_max, config.turn_radius_min)
    return np.array([*values, *bounds], dtype=np.float64)


@functools.lru_cache(maxsize=16)
def _evaluate_params(config: EnvConfig) -> np.ndarray:
    reward, dynamics = config.reward, config.dynamics
    weights = (reward.speed, reward.collision, reward.offroad, reward.risk, reward.comfort)
    values = (TAU_MAX, MAX_INTERACTION_DISTANCE, reward.target_speed, *weights)
    scales = (dynamics.accel_min, dynamics.accel_max, dynamics.yaw_rate_max)
    return np.array([*values, *scales], dtype=np.float64)
