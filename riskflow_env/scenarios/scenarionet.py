"""Recorded scenes in the ScenarioNet / MetaDrive "scenario description" format.

A description is a pickled dict with ``tracks`` (object id -> ``type`` and ``state``:
``position (T, 3)``, ``heading (T,)``, ``velocity (T, 2)``, ``valid (T,)``,
``length / width / height (T, 1)``), ``map_features`` and ``metadata`` (``sdc_id``,
``ts`` or ``sample_rate``...). :func:`load_scenarionet` reads one with a restricted
unpickler (:mod:`~riskflow_env.scenarios.safe_pickle`: builtin containers and numpy
arrays only) and turns it into a :class:`Scenario`:

* Agents: the ``VEHICLE`` tracks; the SDC (``metadata["sdc_id"]``) is the ego, row 0.
  Pedestrians, cyclists, cones and barriers are dropped. A step whose position or
  heading is NaN or inf is read as unobserved (invalid); tracks never valid in the
  window are dropped.
* Time: resampled to 10 Hz when the file's rate differs (linear in position and
  velocity, shortest-arc in heading; a resampled step is valid when both recorded
  neighbours are). nuScenes tracks are 2 Hz keyframes that the converter already
  interpolated to 10 Hz: their accelerations and jerk are interpolation artefacts.
* State ``(x, y, v, psi)``: ``v`` is the norm of ``velocity`` (finite differences of
  the positions when the file has none); ``psi`` is unwrapped along time.
* Window: ``history_steps`` (31) steps up to and including ``current_index`` (default
  30), then the rest of the recording as the reference future, padded to at least
  ``min_future_steps`` (100, one default episode) with invalid steps; a
  ``current_index`` below 30 pads the history the same way. Invalid steps hold the
  nearest valid state (never NaN), with ``valid`` False.
* Sizes: median length and width over the valid steps; 0 and NaN count as not given
  (4.5 x 2.0 m when a track gives none), a negative or infinite size is refused
  (ValueError naming the file, track and field); swapped when the length is the smaller
  (the nuScenes converter stores the SDC's that way).
* Map: :func:`~riskflow_env.scenarios.scenarionet_map.build_map` (every converter's
  lane widths and surfaces, lane centrelines with successors and speed limits), cropped
  to the box of the logged vehicle positions plus a margin that leaves room for a 10 s
  rollout (``crop``, ``crop_margin``). Logged positions beyond the extent of the map
  features are invalid steps (the map knows nothing there). The ground under the logged
  vehicles is drivable even where the map data does not draw it
  (:mod:`~riskflow_env.scenarios.logged_surface`: nuScenes car parks). Traffic lights
  are not used.
* ``smooth=True``: the tracks are replaced by their Savitzky-Golay kinematic reference
  filtering (:mod:`~riskflow_env.scenarios.smoothing`).
* ``map_cache``: the built map is kept on disk, keyed by the file's content hash
  (:mod:`~riskflow_env.scenarios.map_cache`); a whole dataset folder is read by
  :class:`~riskflow_env.scenarios.scenarionet_dataset.ScenarioNetDataset`.
* Arrays must hold real numbers: complex values are refused, not cast.
* Counts (tracks, steps, map features, points) are checked against
  :mod:`~riskflow_env.scenarios.scenarionet_limits` before any array is built; ids
  (``sdc_id``, track and lane ids, the scenario id) are str or int
  (:func:`~riskflow_env.untrusted.entry_id`).

The tracks become arrays (stacking, time stamps, resampling, speeds, holding invalid
steps) in :mod:`~riskflow_env.scenarios.scenarionet_tracks`; the map in
:mod:`~riskflow_env.scenarios.scenarionet_map`.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.config import _finite, _integer, _require
from riskflow_env.scenarios.logged_surface import logged_boxes
from riskflow_env.scenarios.map_cache import MapCache, file_digest
from riskflow_env.scenarios.safe_pickle import (
    errors_name_the_file,
    load_data_pickle,
    loads_data_pickle,
    read_data_file,
)
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet_features import feature_bounds
from riskflow_env.scenarios.scenarionet_limits import MAX_STEPS, check_counts, check_track_steps
from riskflow_env.scenarios.scenarionet_map import build_map
from riskflow_env.scenarios.scenarionet_tracks import (
    DT,
    hold_nearest_valid,
    resample,
    speed_from_xy,
    stack_tracks,
    time_stamps,
)
from riskflow_env.scenarios.smoothing import smooth_tracks
from riskflow_env.state import HISTORY_STEPS
from riskflow_env.untrusted import entry_id

MIN_FUTURE_STEPS = 100  # reference future padded to at least this many steps (10 s)
VEHICLE = "VEHICLE"
ROLLOUT_SECONDS = 10.0  # [s] closed-loop episode the cropped map must leave room for
CROP_MARGIN_RANGE = (50.0, 200.0)  # [m] bounds on the automatic crop margin


def load_scenarionet(
    path: str | Path,
    resolution: float = 0.5,
    current_index: int | None = None,
    min_future_steps: int = MIN_FUTURE_STEPS,
    margin: float = 5.0,
    crop: bool = True,
    crop_margin: float | None = None,
    smooth: bool = False,
    map_cache: MapCache | None = None,
    logged_ground: bool = True,
) -> Scenario:
    """Load one ScenarioNet / MetaDrive scenario-description pickle as a :class:`Scenario`.

    Args:
        path: the ``.pkl`` file. It is read with a restricted unpickler: a file naming
            any global other than builtin containers and numpy array reconstruction
            raises ``ValueError`` without running anything.
        resolution: map raster resolution [m/px].
        current_index: step (at 10 Hz, from the start of the recording) that becomes the
            current one; default ``history_steps - 1`` = 30 (3 s of history).
        min_future_steps: the reference future has at least this many steps [0.1 s].
        margin: off-road border around the road [m].
        crop: crop the map to the logged vehicles' bounding box plus ``crop_margin``;
            False builds the map of the whole recording area.
        crop_margin: [m] > 0 added on every side of the vehicles' bounding box; None:
            the distance covered in :data:`ROLLOUT_SECONDS` at the 95th percentile of
            the logged vehicle speeds, clipped to :data:`CROP_MARGIN_RANGE`.
        smooth: replace the logged tracks by their kinematic reference filtering
            (:func:`~riskflow_env.scenarios.smoothing.smooth_tracks`, Savitzky-Golay);
            False keeps the raw logs.
        map_cache: keep the built map on disk, keyed by the file's content hash and the
            map settings (:class:`~riskflow_env.scenarios.map_cache.MapCache`), and read
            it back instead of building it when the same file is loaded again; None
            builds the map every time.
        logged_ground: make the ground under the logged vehicles drivable where the map
            data does not draw it (:mod:`~riskflow_env.scenarios.logged_surface`); False
            keeps the map data's drivable area alone (to check how well it covers the
            logged vehicles).

    Returns:
        A Scenario named ``"scenarionet/<scenario id>"`` with ``dt`` 0.1 s.

    Raises:
        FileNotFoundError: when ``path`` is not a file.
        ValueError: naming the file, for every malformed, hostile or oversized input
            (whatever the underlying cause: ``MemoryError``, ``IndexError``,
            ``LookupError``, ``TypeError``...).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"load_scenarionet: no such file {path}")
    if path.suffix.lower() == ".npz":
        raise ValueError(
            f"{path}: load_scenarionet reads ScenarioNet pickles; for a RiskFlow .npz scene "
            "use riskflow_env.scenarios.load_scenario(path)"
        )
    if map_cache is None:
        description, digest = load_data_pickle(path), None
    else:
        data = read_data_file(path)
        description, digest = loads_data_pickle(data, str(path)), file_digest(data)
    return scenario_from_description(
        description,
        resolution,
        current_index,
        min_future_steps,
        margin,
        source=str(path),
        crop=crop,
        crop_margin=crop_margin,
        smooth=smooth,
        map_cache=map_cache,
        file_digest=digest,
        logged_ground=logged_ground,
    )


def scenario_from_description(
    description: Mapping[str, Any],
    resolution: float = 0.5,
    current_index: int | None = None,
    min_future_steps: int = MIN_FUTURE_STEPS,
    margin: float = 5.0,
    source: str = "<description>",
    crop: bool = True,
    crop_margin: float | None = None,
    smooth: bool = False,
    map_cache: MapCache | None = None,
    file_digest: str | None = None,
    logged_ground: bool = True,
) -> Scenario:
    """:func:`load_scenarionet` for an already loaded description dict (every failure a
    ``ValueError`` naming ``source``); the map goes through ``map_cache`` when both it
    and ``file_digest`` (the content hash of the description's file) are given."""
    resolution, margin, crop_margin = _check_arguments(
        resolution, current_index, min_future_steps, margin, crop_margin
    )
    cache = (map_cache, file_digest) if map_cache is not None and file_digest else None
    with errors_name_the_file(source, "a readable ScenarioNet scenario"):
        return _scenario(
            description,
            resolution,
            current_index,
            min_future_steps,
            margin,
            source,
            crop,
            crop_margin,
            smooth,
            cache,
            logged_ground,
        )


def _check_arguments(
    resolution: float,
    current_index: int | None,
    min_future_steps: int,
    margin: float,
    crop_margin: float | None,
) -> tuple[float, float, float | None]:
    """``(resolution, margin, crop_margin)`` as Python numbers (numpy scalars taken), or a
    ValueError naming the loader's argument that is out of its range."""
    resolution = _finite("resolution", resolution)
    _require(resolution > 0, f"resolution must be > 0 [m/px], got {resolution!r}")
    if current_index is not None:
        _integer("current_index", current_index, 0)
    _integer("min_future_steps", min_future_steps, 0)
    margin = _finite("margin", margin)
    _require(margin >= 0, f"margin must be >= 0 [m], got {margin!r}")
    if crop_margin is not None:
        crop_margin = _finite("crop_margin", crop_margin)
        _require(crop_margin > 0, f"crop_margin must be > 0 [m], got {crop_margin!r}")
    return resolution, margin, crop_margin


def _scenario(
    description: Mapping[str, Any],
    resolution: float,
    current_index: int | None,
    min_future_steps: int,
    margin: float,
    source: str,
    crop: bool,
    crop_margin: float | None,
    smooth: bool,
    cache: tuple[MapCache, str] | None,
    logged_ground: bool,
) -> Scenario:
    for key in ("tracks", "map_features", "metadata"):
        if not isinstance(description, Mapping) or not isinstance(description.get(key), Mapping):
            raise ValueError(f"{source}: a scenario description needs a dict {key!r}")
    check_counts(description, source)
    tracks, metadata = description["tracks"], description["metadata"]
    by_id = {
        entry_id(k, f"{source}: a VEHICLE track's id"): t
        for k, t in tracks.items()
        if isinstance(t, Mapping) and isinstance(t.get("type"), str) and t["type"] == VEHICLE
    }
    ids = list(by_id)
    sdc = entry_id(metadata.get("sdc_id", ""), f"{source}: metadata['sdc_id']")
    if sdc not in by_id:
        raise ValueError(f"{source}: metadata['sdc_id'] = {sdc!r} is not a VEHICLE track")
    ids.remove(sdc)
    ids.insert(0, sdc)
    states = [by_id[i].get("state") for i in ids]
    xy, heading, velocity, valid, size = stack_tracks(states, ids, source)

    times = time_stamps(metadata, xy.shape[1], source)
    span = (times[-1] - times[0]) / DT
    if span + 1 > MAX_STEPS:
        raise ValueError(
            f"{source}: the recording spans {times[-1] - times[0]:.3g} s = {span + 1:.3g} steps "
            f"at 10 Hz, over the limit MAX_STEPS = {MAX_STEPS}"
        )
    grid = np.arange(int(np.floor((times[-1] - times[0]) / DT + 1e-6)) + 1) * DT + times[0]
    check_track_steps(len(ids), len(grid), source)
    if len(times) != len(grid) or not np.allclose(times, grid, atol=1e-6):
        xy, heading, velocity, valid = resample(times, grid, xy, heading, velocity, valid)
    speed = np.linalg.norm(velocity, axis=-1) if velocity is not None else speed_from_xy(xy, valid)
    coverage = feature_bounds(description["map_features"])
    if coverage is not None:  # beyond the map data nothing is known: not a logged off-road
        valid = valid & _inside(xy, coverage)

    now = HISTORY_STEPS - 1 if current_index is None else int(current_index)
    if not 0 <= now < len(grid):
        raise ValueError(f"current_index must be in [0, {len(grid)}) for {source}, got {now}")
    if not valid[0, now]:
        raise ValueError(
            f"{source}: the SDC {sdc!r} is not valid at current_index {now} (no logged state, "
            "or a position beyond the map features' extent)"
        )
    future = max(len(grid) - now - 1, int(min_future_steps))
    index = now - (HISTORY_STEPS - 1) + np.arange(HISTORY_STEPS + future)
    inside = (index >= 0) & (index < len(grid))
    index = np.clip(index, 0, len(grid) - 1)
    window_valid = valid[:, index] & inside
    keep = window_valid.any(axis=1)
    keep[0] = True
    states = np.concatenate(
        [xy[:, index], speed[:, index, None], heading[:, index, None]], axis=-1
    )[keep]
    window_valid = window_valid[keep]
    if smooth:
        states = smooth_tracks(states, window_valid, DT)
    states = hold_nearest_valid(states, window_valid)
    states[..., 3] = np.unwrap(states[..., 3], axis=1)
    length, width = size[keep, 0], size[keep, 1]
    scenario_id = metadata.get("scenario_id", metadata.get("id", description.get("id", "")))
    name = entry_id(scenario_id, f"{source}: the scenario id")
    all_xy = xy[valid]
    region = _crop_region(all_xy, speed[valid], crop_margin, source) if crop else None
    build = functools.partial(
        build_map,
        description["map_features"],
        resolution,
        margin,
        f"scenarionet/{name}",
        all_xy,
        source,
        region=region,
        logged=logged_boxes(xy, heading, valid, size[:, 0], size[:, 1]) if logged_ground else None,
    )
    if cache is None:
        drivable_map = build()
    else:
        map_cache, digest = cache
        settings = {
            "resolution": float(resolution),
            "margin": float(margin),
            "region": region,
            "logged_ground": bool(logged_ground),
        }
        key = map_cache.key(digest, name=f"scenarionet/{name}", **settings)
        drivable_map = map_cache.get_or_build(key, build)
    return Scenario(
        map=drivable_map,
        states=states,
        valid=window_valid,
        length=length,
        width=width,
        ego_index=0,
        agent_ids=tuple(i for i, kept in zip(ids, keep.tolist(), strict=True) if kept),
        name=f"scenarionet/{name}",
        dt=DT,
        history_steps=HISTORY_STEPS,
    )


def _crop_region(
    xy: np.ndarray, speed: np.ndarray, crop_margin: float | None, source: str
) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) [m]: the box of the valid vehicle positions ``xy`` (P, 2)
    grown by ``crop_margin`` (None: see :func:`load_scenarionet`)."""
    if crop_margin is None:
        reach = ROLLOUT_SECONDS * float(np.percentile(speed, 95)) if speed.size else 0.0
        crop_margin = float(np.clip(reach, *CROP_MARGIN_RANGE))
    low, high = xy.min(axis=0) - crop_margin, xy.max(axis=0) + crop_margin
    return float(low[0]), float(low[1]), float(high[0]), float(high[1])


def _inside(xy: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """(...) bool: points ``xy`` (..., 2) [m] inside ``box`` (xmin, ymin, xmax, ymax)."""
    x, y = xy[..., 0], xy[..., 1]
    return (x >= box[0]) & (x <= box[2]) & (y >= box[1]) & (y <= box[3])
