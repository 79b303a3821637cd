"""Scene-centric training windows as a torch ``Dataset``, batching, action normalisation.

Windows follow docs/how-to/windows.md and are built by
:func:`policies.learned.windows.window_from_scenario`, once, when the dataset is
made; they are packed into a few flat arrays (agents of all windows end to end), so
``__getitem__`` only slices. ``cache_path`` keeps the packed arrays in an ``.npz`` file,
rebuilt when the scenes, the config or the stride change.

Normalisation statistics (per-channel mean and std of the valid ``actions``) are computed
once over the training split and kept as ``norm_stats.json`` beside the data, or in the
user cache for the shipped bank (:func:`load_or_compute_stats`, ``data_cache``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import os
import warnings
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from torch import Tensor
from torch.utils.data import Dataset

from policies.learned.data_cache import derived_dir
from policies.learned.parked import add_parked
from policies.learned.recovery import RecoveryConfig, perturb_tracks
from policies.learned.window_types import AGENT_FIELDS, PAIR_FIELDS, Window
from policies.learned.windows import WindowConfig, select_rows, window_from_scenario
from riskflow_env._array import Array, asarray_like
from riskflow_env.atomic_files import atomic_file, write_text
from riskflow_env.config import is_integer
from riskflow_env.dynamics import ACTION_DIM
from riskflow_env.folder_lock import make_output_file
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset

STATS_FILENAME = "norm_stats.json"
# The packed arrays (and the cache file) are keyed by the Window field names; the layout
# is unchanged since version 1, so caches written before Window existed stay valid.
_CACHE_VERSION = 1


def window_indices(scenario: Scenario, config: WindowConfig, stride: int) -> np.ndarray:
    """Current steps of the windows cut from ``scenario``.

    From ``history_steps - 1`` to ``T - future_steps - 1`` (full history and future fit)
    every ``stride`` steps, where the ego is valid.

    Returns:
        (W,) int64 indices into ``scenario.states``' time axis.
    """
    stop = scenario.states.shape[1] - config.future_steps
    steps = np.arange(config.history_steps - 1, stop, stride, dtype=np.int64)
    return steps[scenario.valid[scenario.ego_index, steps]]


Folder = str | os.PathLike | ScenarioNetDataset
"""One folder of scenes: a directory of ``.npz`` scene files or a ScenarioNet dataset."""


def _scenes(
    source: Sequence[Scenario] | Folder | Sequence[Folder],
    cache_path: str | os.PathLike | None,
) -> tuple[list[Any], Iterator]:
    """(fingerprint parts, iterator over scenes) of an in-memory list, a directory, a
    ScenarioNet dataset (each scene read when the iterator reaches it) or a sequence of
    directories and datasets (their scenes one folder after the other, in the given order)."""
    if _is_folders(source):
        pieces = [_scenes(folder, cache_path) for folder in source]
        return [parts for parts, _ in pieces], itertools.chain(*(it for _, it in pieces))
    if isinstance(source, ScenarioNetDataset):
        return source.fingerprint(), (source.load(i) for i in range(len(source)))
    if isinstance(source, (str, os.PathLike)):
        from riskflow_env.scenarios.io import list_scenarios, load_scenario  # lazy: optional

        cache = Path(cache_path).resolve() if cache_path is not None else None
        paths = [p for p in list_scenarios(source) if Path(p).resolve() != cache]
        parts = [[p.name, p.stat().st_size, p.stat().st_mtime_ns] for p in map(Path, paths)]
        return parts, (load_scenario(path) for path in paths)
    scenes = list(source)
    if not all(isinstance(scene, Scenario) for scene in scenes):
        raise TypeError(
            "source must be a directory, a ScenarioNet dataset, a sequence of those, or a "
            "sequence of Scenario objects"
        )
    parts = [
        [s.name, hashlib.sha1(s.states.tobytes() + s.valid.tobytes()).hexdigest()] for s in scenes
    ]
    return parts, iter(scenes)


def _is_folders(source: object) -> bool:
    """Whether ``source`` is a non-empty list or tuple of folders (not of scenes)."""
    folder_types = (str, os.PathLike, ScenarioNetDataset)
    return (
        isinstance(source, (list, tuple))
        and len(source) > 0
        and all(isinstance(item, folder_types) for item in source)
    )


def _pack(windows: list[Window]) -> dict[str, np.ndarray]:
    """Windows end to end, keyed by field name: agent fields along A, pair fields
    flattened to (A * A, ...); ``agent_offsets`` / ``pair_offsets`` (W + 1,) mark where
    each window starts."""
    counts = np.array([w.num_agents for w in windows], dtype=np.int64)
    packed = {name: np.concatenate([getattr(w, name) for w in windows]) for name in AGENT_FIELDS}
    for name in PAIR_FIELDS:
        arrays = [getattr(w, name) for w in windows]
        packed[name] = np.concatenate([a.reshape(-1, *a.shape[2:]) for a in arrays])
    packed["agent_offsets"] = np.concatenate([[0], np.cumsum(counts)])
    packed["pair_offsets"] = np.concatenate([[0], np.cumsum(counts**2)])
    return packed


class WindowDataset(Dataset):
    """Training windows of a set of scenes, several per scene.

    Args:
        source: scenes in memory, a directory read with
            ``riskflow_env.scenarios.io.list_scenarios`` / ``load_scenario``, a
            ``ScenarioNetDataset`` (scenes read one at a time: only the windows stay), or a
            list of directories and datasets (one folder's scenes after the other's;
            scene positions run on across them).
        config: window options (sizes, agent selection).
        stride: steps between the current steps of consecutive windows of a scene.
        cache_path: optional ``.npz`` file holding the packed windows; used when it
            matches the scenes, config, stride and recovery, written otherwise (it may sit
            in the scene directory: it is not read as a scene).
        recovery: add ``recovery.copies`` recovery windows per window (agents that drift
            off their log and return: :mod:`policies.learned.recovery`; ``recovery.parked``
            parked cars: :mod:`policies.learned.parked`); copy ``k`` of
            the window of scene ``s`` at step ``c`` draws from ``(seed, s, c, k)``.

    Items are :class:`~policies.learned.window_types.Window` objects with the future
    fields, A varying per item (:func:`~policies.learned.window_types.collate_windows`
    batches them); their arrays are views into the dataset's, so do not modify them in
    place. ``index[i] = (scene position, current step)`` of item i.
    """

    def __init__(
        self,
        source: Sequence[Scenario] | Folder | Sequence[Folder],
        config: WindowConfig | None = None,
        stride: int = 5,
        cache_path: str | os.PathLike | None = None,
        recovery: RecoveryConfig | None = None,
    ) -> None:
        if not is_integer(stride) or stride < 1:
            raise ValueError(f"stride must be an int >= 1 [steps], got {stride!r}")
        if recovery is not None and not isinstance(recovery, RecoveryConfig):
            raise TypeError(f"recovery must be a RecoveryConfig or None, got {recovery!r}")
        self.config = config or WindowConfig()
        self.stride = stride = int(stride)  # a numpy int as a Python one (the fingerprint)
        self.recovery = recovery if recovery is not None and recovery.copies else None
        parts, scenes = _scenes(source, cache_path)
        settings = [_CACHE_VERSION, dataclasses.asdict(self.config), stride, parts]
        if self.recovery is not None:  # caches without recovery keep their fingerprint
            settings.append(self.recovery.settings())
        fingerprint = hashlib.sha256(json.dumps(settings).encode()).hexdigest()
        packed = _load_cache(cache_path, fingerprint) if cache_path is not None else None
        if packed is None:
            packed = self._build(scenes)
            if cache_path is not None:
                with atomic_file(cache_path) as file:  # np.savez would append ".npz" to a path
                    np.savez(file, fingerprint=np.array(fingerprint), **packed)
        self.index = packed.pop("index")
        self._agent_offsets = packed.pop("agent_offsets")
        self._pair_offsets = packed.pop("pair_offsets")
        self._arrays = packed

    def _build(self, scenes: Iterator[Scenario]) -> dict[str, np.ndarray]:
        windows, index = [], []
        for position, scenario in enumerate(scenes):
            for current in window_indices(scenario, self.config, self.stride):
                windows.append(window_from_scenario(scenario, int(current), self.config))
                index.append((position, int(current)))
                for copy in range(self.recovery.copies if self.recovery else 0):
                    windows.append(self._recovery_window(scenario, position, int(current), copy))
                    index.append((position, int(current)))
        if not windows:
            raise ValueError(
                "WindowDataset: no window fits (scenes need history_steps + future_steps "
                f"= {self.config.history_steps + self.config.future_steps} steps with the "
                "ego valid at the current step)"
            )
        packed = _pack(windows)
        packed["index"] = np.array(index, dtype=np.int64).reshape(-1, 2)
        return packed

    def _recovery_window(
        self, scenario: Scenario, position: int, current: int, copy: int
    ) -> Window:
        recovery = self.recovery
        assert recovery is not None
        rng = np.random.default_rng([recovery.seed, position, current, copy])
        rows = select_rows(scenario, current, self.config)
        states = perturb_tracks(
            scenario.states, scenario.valid, rows, current, scenario.dt, recovery, rng,
            self.config.dynamics.yaw_rate_max,
        )  # fmt: skip
        moved = dataclasses.replace(scenario, states=states.astype(scenario.states.dtype))
        turn, jitter = recovery.parked_turn, recovery.parked_jitter
        moved = add_parked(moved, recovery.parked, current, rng, turn=turn, jitter=jitter)
        return window_from_scenario(moved, current, self.config)

    def __len__(self) -> int:
        return len(self.index)

    def window(self, item: int) -> Window:
        """Window ``item`` (numpy views into the packed arrays)."""
        if not -len(self) <= item < len(self):
            raise IndexError(f"window index {item} out of range for {len(self)} windows")
        item %= len(self)
        a0, a1 = self._agent_offsets[item : item + 2]
        p0, p1 = self._pair_offsets[item : item + 2]
        fields = {name: self._arrays[name][a0:a1] for name in AGENT_FIELDS}
        for name in PAIR_FIELDS:
            array = self._arrays[name][p0:p1]
            fields[name] = array.reshape(a1 - a0, a1 - a0, *array.shape[1:])
        return Window(**fields)

    def __getitem__(self, item: int) -> Window:
        return self.window(item)

    def agent_counts(self) -> np.ndarray:
        """(W,) int64 agents ``A`` of each window."""
        return np.diff(self._agent_offsets)

    def valid_actions(self) -> np.ndarray:
        """(M, 2) float32 every valid action of every window (for statistics)."""
        return self._arrays["actions"][self._arrays["actions_valid"]]


def _load_cache(path: str | os.PathLike, fingerprint: str) -> dict[str, np.ndarray] | None:
    """The packed windows of the cache file, or None: no file, another fingerprint, or a
    file that cannot be read (a warning; the windows are rebuilt and the file rewritten)."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
            if "fingerprint" not in data or str(data["fingerprint"]) != fingerprint:
                return None
            return {key: data[key] for key in data.files if key != "fingerprint"}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        warnings.warn(
            f"window cache {path} cannot be read ({type(error).__name__}: {error}); rebuilding it",
            UserWarning,
            stacklevel=3,
        )
        return None


class Normalizer(Protocol):
    """Per-channel action normalisation (:class:`ActionNormalizer` is one)."""

    def normalize(self, actions: Tensor) -> Tensor:
        """Physical ``(..., 2)`` (accel [m/s^2], yaw rate [rad/s]) -> normalised."""
        ...

    def denormalize(self, actions: Tensor) -> Tensor:
        """Normalised ``(..., 2)`` -> physical units."""
        ...


@dataclass(frozen=True)
class ActionNormalizer:
    """Per-channel affine normalisation of actions: ``z = (a - mean) / std``.

    Attributes:
        mean: (accel [m/s^2], yaw rate [rad/s]) means of the valid training actions.
        std: their standard deviations (> 0; floored when computed).
        count: number of actions the statistics come from.
    """

    mean: tuple[float, float]
    std: tuple[float, float]
    count: int = 0

    def __post_init__(self) -> None:
        mean, std = tuple(map(float, self.mean)), tuple(map(float, self.std))
        if len(mean) != ACTION_DIM or len(std) != ACTION_DIM:
            raise ValueError(f"ActionNormalizer needs {ACTION_DIM} means and stds, got {mean, std}")
        if not all(map(math.isfinite, mean + std)) or min(std) <= 0:
            raise ValueError(f"ActionNormalizer: mean must be finite, std > 0; got {mean, std}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "std", std)

    def _params(self, like: Array) -> tuple[Array, Array]:
        if like.shape[-1] != ACTION_DIM:
            raise ValueError(f"actions must have shape (..., {ACTION_DIM}), got {like.shape}")
        return asarray_like(self.mean, like), asarray_like(self.std, like)

    def normalize(self, actions: Array) -> Array:
        """``(..., 2)`` actions [m/s^2, rad/s] -> normalised, numpy or torch."""
        mean, std = self._params(actions)
        return (actions - mean) / std

    def denormalize(self, normalized: Array) -> Array:
        """Inverse of :meth:`normalize`: ``(..., 2)`` -> actions [m/s^2, rad/s]."""
        mean, std = self._params(normalized)
        return normalized * std + mean

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {"mean": list(self.mean), "std": list(self.std), "count": self.count}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ActionNormalizer:
        """From :meth:`to_dict`'s output."""
        missing = {"mean", "std"} - set(data)
        if missing:
            raise ValueError(f"action statistics miss {sorted(missing)}")
        return cls(tuple(data["mean"]), tuple(data["std"]), int(data.get("count", 0)))

    def save(self, path: str | os.PathLike) -> None:
        """Write the statistics as JSON."""
        write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> ActionNormalizer:
        """Read statistics written by :meth:`save`."""
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except (json.JSONDecodeError, TypeError, ValueError) as err:
            raise ValueError(f"malformed action statistics file {path}: {err}") from None


def compute_action_stats(
    dataset: WindowDataset | Sequence[Window], min_std: float = 1e-3
) -> ActionNormalizer:
    """Per-channel mean and std of the valid actions of ``dataset`` (float64 sums).

    Args:
        dataset: a :class:`WindowDataset` (read from its packed arrays) or any sequence of
            windows with the future fields.
        min_std: floor on the std (a channel that never varies, e.g. accel of
            constant-speed traffic, would otherwise divide by ~0) [m/s^2, rad/s].
    """
    if isinstance(dataset, WindowDataset):
        actions = dataset.valid_actions()
    else:
        chunks = [np.asarray(w.actions)[np.asarray(w.actions_valid)] for w in dataset]
        actions = np.concatenate(chunks) if chunks else np.zeros((0, ACTION_DIM))
    if actions.shape[0] == 0:
        raise ValueError("compute_action_stats: the dataset has no valid action")
    actions = actions.astype(np.float64)
    std = np.maximum(actions.std(axis=0), min_std)
    return ActionNormalizer(tuple(actions.mean(axis=0)), tuple(std), int(actions.shape[0]))


def load_or_compute_stats(
    directory: str | os.PathLike, dataset: WindowDataset | Sequence[Window]
) -> ActionNormalizer:
    """``directory/norm_stats.json`` if present, else computed over ``dataset`` and saved.

    Pass the training split: the statistics are computed once and then reused. A
    ``directory`` inside the installed packages or not writable keeps them in the user
    cache instead (:func:`policies.learned.data_cache.derived_dir`).
    """
    path = derived_dir(directory) / STATS_FILENAME
    if path.is_file():
        return ActionNormalizer.load(path)
    normalizer = compute_action_stats(dataset)
    normalizer.save(make_output_file(path))
    return normalizer


__all__ = [
    "STATS_FILENAME",
    "ActionNormalizer",
    "WindowDataset",
    "compute_action_stats",
    "load_or_compute_stats",
    "window_indices",
]
