"""Scenario files: a versioned, compressed ``.npz`` format, banks and the shipped scenes.

One scene per file (``schema="riskflow-scenario"``, ``version=1``), read with
``allow_pickle=False``:

=====================  =================  ===============================================
key                    shape, dtype       meaning
=====================  =================  ===============================================
schema, version        (), str / int      ``"riskflow-scenario"``, ``1``
name, source, family   (), str            :class:`Scenario` labels
dt, history_steps      (), float / int    time step [s], history length (current incl.)
ego_index              (), int            row of the ego
states                 (N, T, 4) float    x [m], y [m], v [m/s], psi [rad]; float32 when
                                          that is lossless, else float64; 0 where invalid
valid                  (N, T) bool        observed states
length, width          (N,) float64       vehicle sizes [m]
agent_ids, kinds       (N,) or (0,) str   per-agent labels
map_*                  see below          the map, stored inline ...
map_ref, map_hash      (), str            ... or a path to a map file, relative to this
                                          file's folder, and the map's content hash
=====================  =================  ===============================================

A map is stored inline with the ``map_`` prefix, or alone in a ``schema="riskflow-map"``
file: its arrays and map files are :mod:`~riskflow_env.scenarios.map_files`
(``load_map``, ``map_to_arrays``, ``map_hash``... are re-exported here).

Banks: a folder of scene files; ``save_scenario(..., map_dir=folder / "maps")`` writes
each distinct map once, as ``maps/<hash>.npz`` (16 hex digits of a SHA-256 of its
arrays), and loading keeps one in-memory copy per hash, shared by all scenes.
Files are written to a temporary name and renamed (atomic), with fixed zip timestamps,
so equal scenes give byte-identical files.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from riskflow_env.folder_lock import file_path, make_output_file, make_output_folder
from riskflow_env.scenarios._npz import (
    VERSION,
    ScenarioFormatError,
    check_arrays,
    read_npz,
    write_npz,
)
from riskflow_env.scenarios.map_files import (
    MAP_KEYS,
    MAP_LIMITS,
    MAP_SCHEMA,
    OPTIONAL_MAP_KEYS,
    check_sdf_budget,
    load_map,
    map_from_arrays,
    map_hash,
    map_to_arrays,
    read_map,
    read_map_arrays,
    string_array,
    write_map_arrays,
)
from riskflow_env.scenarios.scenario import MAX_STEPS, MAX_TRACKS, Scenario
from riskflow_env.scenarios.sources import ScenarioBank

SCHEMA = "riskflow-scenario"
ASSETS = Path(__file__).resolve().parent.parent / "assets" / "scenarios"
SPLITS = ("eval", "train")
# key -> (shape with named dims, allowed dtype kinds: f float, b bool, i/u int, U str)
_SCENE_KEYS = {
    "name": ((), "U"),
    "source": ((), "U"),
    "family": ((), "U"),
    "dt": ((), "f"),
    "history_steps": ((), "iu"),
    "ego_index": ((), "iu"),
    "states": (("N", "T", 4), "f"),
    "valid": (("N", "T"), "b"),
    "length": (("N",), "f"),
    "width": (("N",), "f"),
    "agent_ids": (("N?",), "U"),
    "kinds": (("N?",), "U"),
}
_REF_KEYS = {"map_ref": ((), "U"), "map_hash": ((), "U")}
# named dim -> (limit's name, value), checked from the .npy headers before anything is loaded
_SCENE_LIMITS = {"N": ("MAX_TRACKS", MAX_TRACKS), "T": ("MAX_STEPS", MAX_STEPS)}


def save_scenario(
    scenario: Scenario,
    path: str | os.PathLike,
    map_dir: str | os.PathLike | None = None,
    include_sdf: bool = False,
) -> Path:
    """Write ``scenario`` to ``path`` (``.npz``); returns the path.

    Args:
        scenario: the scene.
        path: destination file (its folder is created when missing).
        map_dir: where shared maps live (e.g. ``<bank>/maps``); the map is written there
            as ``<hash>.npz`` when absent and referenced by a relative path. None stores
            the map inside the scene file.
        include_sdf: also store the map's SDF (float32, compresses poorly) instead of
            recomputing it from the raster on load.
    """
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be a Scenario, got {type(scenario).__name__}")
    path = make_output_file(file_path(path))
    arrays: dict[str, np.ndarray] = {"schema": np.array(SCHEMA), "version": np.array(VERSION)}
    states = np.where(scenario.valid[..., None], scenario.states, 0.0)  # 0 where invalid
    lossless32 = np.array_equal(states.astype(np.float32).astype(np.float64), states)
    arrays.update(
        name=np.array(scenario.name),
        source=np.array(scenario.source),
        family=np.array(scenario.family),
        dt=np.array(float(scenario.dt)),
        history_steps=np.array(int(scenario.history_steps)),
        ego_index=np.array(int(scenario.ego_index)),
        states=states.astype(np.float32 if lossless32 else np.float64),
        valid=scenario.valid.astype(bool),
        length=scenario.length.astype(np.float64),
        width=scenario.width.astype(np.float64),
        agent_ids=string_array(scenario.agent_ids),
        kinds=string_array(scenario.kinds),
    )
    map_arrays = map_to_arrays(scenario.map, include_sdf)
    if map_dir is None:
        arrays.update({f"map_{key}": value for key, value in map_arrays.items()})
    else:
        map_dir = Path(map_dir)
        digest = map_hash(map_arrays)
        map_path = map_dir / f"{digest}.npz"
        if not map_path.exists():
            make_output_folder(map_dir, "map_dir")
            write_map_arrays(map_path, map_arrays)
        arrays["map_ref"] = np.array(os.path.relpath(map_path, path.parent))
        arrays["map_hash"] = np.array(digest)
    write_npz(path, arrays)
    return path


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read a scene written by :func:`save_scenario`.

    Raises:
        FileNotFoundError: no such file (or its referenced map file is missing).
        ScenarioFormatError: unexpected zip members or keys, sizes or counts over the
            limits (checked from the zip and ``.npy`` headers before anything is
            decompressed: :mod:`~riskflow_env.scenarios._npz`, ``MAX_TRACKS``,
            ``MAX_STEPS``, ``MAP_LIMITS``), wrong schema or version, missing keys, wrong
            shapes or dtypes, NaN/inf at valid steps, values out of their ranges
            (:class:`Scenario`, :class:`~riskflow_env.maps.DrivableMap`), or an invalid
            map; the message names the file. States at invalid steps read as 0.
            A ``.pkl`` file (a ScenarioNet pickle) is refused with a pointer to
            :func:`riskflow_env.scenarios.scenarionet.load_scenarionet`.
    """
    path = file_path(path)
    if path.suffix.lower() == ".pkl":
        raise ScenarioFormatError(
            f"{path}: load_scenario reads RiskFlow .npz scenario files; for a ScenarioNet "
            "pickle use riskflow_env.scenarios.scenarionet.load_scenarionet(path)"
        )
    arrays = read_npz(path, SCHEMA, _check_scene_members)
    if "map_ref" in arrays:
        ref = _map_ref_path(path, str(arrays["map_ref"]))
        drivable_map = load_map(ref, expected_hash=str(arrays["map_hash"]))
    else:
        map_arrays = {key[4:]: value for key, value in arrays.items() if key.startswith("map_")}
        drivable_map = map_from_arrays(path, map_arrays)
    valid = arrays["valid"]
    states = np.where(valid[..., None], arrays["states"].astype(np.float64), 0.0)  # as saved
    bad = np.argwhere(valid & ~np.all(np.isfinite(states), axis=-1))
    if bad.size:
        agent, step = (int(v) for v in bad[0])
        raise ScenarioFormatError(
            f"{path}: 'states' has NaN or inf at {len(bad)} valid step(s), "
            f"first at agent {agent}, step {step}"
        )
    try:
        return Scenario(
            map=drivable_map,
            states=states,
            valid=valid,
            length=arrays["length"].astype(np.float64),
            width=arrays["width"].astype(np.float64),
            ego_index=int(arrays["ego_index"]),
            agent_ids=tuple(str(v) for v in arrays["agent_ids"]),
            name=str(arrays["name"]),
            dt=float(arrays["dt"]),
            history_steps=int(arrays["history_steps"]),
            kinds=tuple(str(v) for v in arrays["kinds"]),
            source=str(arrays["source"]),
            family=str(arrays["family"]),
        )
    except (ValueError, TypeError) as error:
        raise ScenarioFormatError(f"{path}: {error}") from None


def _check_scene_members(path: Path, members) -> None:
    """A scene file's keys, dtypes, shapes and counts (``MAX_TRACKS``, ``MAX_STEPS``, the
    map's ``MAP_LIMITS``), from the ``.npy`` headers, before anything is loaded."""
    if "map_ref" in members:
        check_arrays(path, members, {**_SCENE_KEYS, **_REF_KEYS}, limits=_SCENE_LIMITS)
    else:
        prefixed = {f"map_{key}": rule for key, rule in MAP_KEYS.items()}
        optional = {f"map_{key}": rule for key, rule in OPTIONAL_MAP_KEYS.items()}
        limits = _SCENE_LIMITS | MAP_LIMITS
        check_arrays(path, members, {**_SCENE_KEYS, **prefixed}, optional, limits)
        check_sdf_budget(path, members, prefix="map_")


def _map_ref_path(path: Path, ref: str) -> Path:
    """The map file that a scene's ``map_ref`` names: a relative path that stays inside
    the scene's folder (absolute paths and ``..`` escapes raise ScenarioFormatError)."""
    relative = Path(ref)
    folder = path.parent.resolve()
    target = (folder / relative).resolve()
    if not ref or relative.is_absolute() or ".." in relative.parts or "\x00" in ref:
        raise ScenarioFormatError(
            f"{path}: map_ref {ref!r} must be a relative path inside the scene's folder"
        )
    if not target.is_relative_to(folder):
        raise ScenarioFormatError(f"{path}: map_ref {ref!r} leaves the scene's folder")
    return path.parent / relative


def list_scenarios(directory: str | os.PathLike) -> list[Path]:
    """Sorted paths of the scene files (``*.npz``) directly in ``directory``.

    Raises:
        FileNotFoundError: ``directory`` does not exist.
        NotADirectoryError: ``directory`` is a file (the message names the loader of one
            file: :func:`load_scenario` for ``.npz``, ``load_scenarionet`` for ``.pkl``).
    """
    directory = Path(directory)
    if directory.is_file():
        raise NotADirectoryError(
            f"{directory} is a file, not a scenario directory (a folder of .npz scene files "
            f"written by riskflow-data generate); {ONE_FILE}"
        )
    if not directory.is_dir():
        raise FileNotFoundError(f"scenario directory {directory} does not exist")
    return sorted(path for path in directory.glob("*.npz") if path.is_file())


def require_scenarios(directory: str | os.PathLike) -> list[Path]:
    """:func:`list_scenarios`, and FileNotFoundError when ``directory`` holds no scene file
    (the message says when it holds ScenarioNet pickles instead)."""
    paths = list_scenarios(directory)
    if not paths:
        pickles = any(Path(directory).glob("*.pkl"))
        hint = f": it holds ScenarioNet pickles (*.pkl); {ONE_FILE}" if pickles else ""
        raise FileNotFoundError(f"no scenario files (*.npz) in {directory}{hint}")
    return paths


def load_bank(directory: str | os.PathLike) -> ScenarioBank:
    """All scenes of ``directory`` (see :func:`require_scenarios`) as a :class:`ScenarioBank`."""
    return ScenarioBank([load_scenario(path) for path in require_scenarios(directory)])


ONE_FILE = (  # how to load one scene, for errors where a folder was expected
    "load one scene with riskflow_env.scenarios.load_scenario (.npz) or "
    "riskflow_env.scenarios.scenarionet.load_scenarionet (ScenarioNet .pkl)"
)


def shipped_bank(split: str = "eval") -> ScenarioBank:
    """The scenes that ship with the package (``riskflow_env/assets/scenarios/<split>``).

    Args:
        split: ``"eval"`` (the default scenarios of ``riskflow_env.parallel_env()``) or
            ``"train"`` (a small training sample). Loaded once, then cached.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return _shipped(split)


@functools.cache
def _shipped(split: str) -> ScenarioBank:
    return load_bank(ASSETS / split)


__all__ = [
    "ASSETS",
    "MAP_SCHEMA",
    "SCHEMA",
    "SPLITS",
    "list_scenarios",
    "load_bank",
    "load_map",
    "load_scenario",
    "map_hash",
    "map_to_arrays",
    "read_map",
    "read_map_arrays",
    "require_scenarios",
    "save_scenario",
    "shipped_bank",
    "write_map_arrays",
]
