"""Hostile scene and map archives (issue 53): refused from their zip and ``.npy`` headers,
or loaded, within a CPU-time bound and 500 MB, whatever they declare.

Every file is built here, small, and loaded by ``load_scenario`` / ``load_map`` in a child
process whose address space is capped at 1.5 GB (:mod:`tests.capped`).
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from riskflow_env.scenarios._npz import write_npz
from riskflow_env.scenarios.io import ASSETS, load_scenario, save_scenario
from tests.capped import Outcome, assert_bounded, run_capped

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

SETUP = "from riskflow_env.scenarios.io import load_map, load_scenario"
SCENE = sorted((ASSETS / "eval").glob("*.npz"))[0]
MAP = sorted((ASSETS / "eval" / "maps").glob("*.npz"))[0]
BOMB = 600 * 2**20  # [bytes] what a bomb member decompresses to (over every limit)


def _refused(outcome: Outcome, path: Path, *fragments: str) -> None:
    """A ScenarioFormatError naming ``path`` and every fragment, one short message, within
    a CPU-time bound and 500 MB."""
    assert outcome.error == "ScenarioFormatError", outcome
    assert path.name in outcome.message and outcome.chars < 1000, outcome
    for fragment in fragments:
        assert fragment in outcome.message, (fragment, outcome.message)
    assert_bounded(outcome)


def _load(path: Path, loader: str = "load_scenario") -> Outcome:
    return run_capped(SETUP, f"{loader}({str(path)!r})")


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


def _inline_scene(tmp_path: Path) -> dict[str, np.ndarray]:
    """The arrays of a shipped scene with its map stored inline."""
    return _arrays(save_scenario(load_scenario(SCENE), tmp_path / "inline.npz"))


def _zip(path: Path, members: dict[str, bytes | int], method: int = zipfile.ZIP_DEFLATED):
    """A zip of ``members``: bytes as they are, an int ``n`` as ``n`` zero bytes (a bomb)."""
    with zipfile.ZipFile(path, "w", compression=method, compresslevel=1) as archive:
        for name, content in members.items():
            with archive.open(name, "w", force_zip64=True) as handle:
                if isinstance(content, bytes):
                    handle.write(content)
                    continue
                chunk = bytes(16 * 2**20)
                for start in range(0, content, len(chunk)):
                    handle.write(chunk[: content - start])
    return path


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, array)
    return buffer.getvalue()


def _header(shape: tuple, descr: str | list = "<f8") -> bytes:
    """A ``.npy`` header declaring ``shape`` and ``descr``, without data."""
    buffer = io.BytesIO()
    header = {"descr": descr, "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buffer, header)
    return buffer.getvalue()


def _members(arrays: dict[str, np.ndarray]) -> dict[str, bytes | int]:
    return {f"{key}.npy": _npy(value) for key, value in arrays.items()}


# --- members refused from the zip directory, before anything is decompressed ---------


def test_member_without_npy_name_refused_not_skipped(tmp_path):
    path = _zip(tmp_path / "blob.npz", _members(_inline_scene(tmp_path)) | {"blob": BOMB})
    assert path.stat().st_size < 5 * 2**20
    _refused(_load(path), path, "'blob'", "unexpected zip member")


def test_member_decompressing_past_the_limit_refused(tmp_path):
    members = _members(_inline_scene(tmp_path))
    members["states.npy"] = BOMB  # decompresses to 600 MiB
    path = _zip(tmp_path / "bomb.npz", members)
    _refused(_load(path), path, "'states.npy'", "MAX_MEMBER_BYTES")


def test_members_together_past_the_limit_refused(tmp_path):
    members = _members(_inline_scene(tmp_path))
    for key in ("agent_ids", "kinds", "map_lane_ids"):
        members[f"{key}.npy"] = 200 * 2**20
    path = _zip(tmp_path / "total.npz", members)
    _refused(_load(path), path, "MAX_FILE_ARRAY_BYTES")


@pytest.mark.parametrize(
    ("header", "fragment"),
    [
        (_header((40_000_000,)), "MAX_MEMBER_BYTES"),  # 320 MB of float64
        (_header((70_000_000,), "|b1"), "MAX_MEMBER_ELEMENTS"),
        (_header((2,), "|O"), "dtype"),
        (_header((2,), [("a", "<f8")]), "dtype"),
        (_header((2, 1, 1, 1, 1)), "MAX_DIMS"),
        (_header((1,), "<U100000"), "MAX_STRING_CHARS"),
        (_header((10,)) + bytes(1000), "declares 80 bytes"),  # more data than declared
    ],
)
def test_member_header_refused_before_its_data(tmp_path, header, fragment):
    members = _members(_inline_scene(tmp_path))
    members["states.npy"] = header + bytes(64)
    path = _zip(tmp_path / "header.npz", members)
    _refused(_load(path), path, "'states'", fragment)


def test_many_members_refused_from_the_end_record(tmp_path):
    members = {f"k{i}.npy": b"" for i in range(20_000)}
    path = _zip(tmp_path / "many.npz", members, zipfile.ZIP_STORED)
    _refused(_load(path), path, "MAX_MEMBERS")


@pytest.mark.parametrize("method", [zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
def test_other_compression_refused(tmp_path, method):
    path = _zip(tmp_path / "bz.npz", _members(_inline_scene(tmp_path)), method)
    _refused(_load(path), path, "expected stored or deflated")


def test_duplicate_member_refused(tmp_path):
    path = tmp_path / "twice.npz"
    with pytest.warns(UserWarning, match="Duplicate name"):
        with zipfile.ZipFile(path, "w") as archive:
            for name, content in _members(_inline_scene(tmp_path)).items():
                archive.writestr(name, content)
            archive.writestr("states.npy", _npy(np.zeros((1, 1, 4))))
    _refused(_load(path), path, "appears twice")


def test_unexpected_key_refused(tmp_path):
    path = tmp_path / "extra.npz"
    write_npz(path, _inline_scene(tmp_path) | {"payload": np.zeros(3)})
    _refused(_load(path), path, "unexpected key", "payload")


# --- counts checked from the headers against the documented limits ---------------------


def test_million_lanes_refused_before_lanes_are_built(tmp_path):
    lanes = 1_000_000
    arrays = _arrays(MAP) | {
        "lane_points": np.zeros((2 * lanes, 2)),
        "lane_offsets": np.arange(0, 2 * lanes + 1, 2),
        "lane_widths": np.full(lanes, 3.5),
        "lane_ids": np.zeros(lanes, dtype="<U1"),
        "lane_speed_limits": np.full(lanes, np.nan),
        "lane_successors": np.zeros(0, dtype="<U1"),
        "lane_successor_offsets": np.zeros(lanes + 1, dtype=np.int64),
    }
    path = tmp_path / "lanes.npz"
    write_npz(path, arrays)
    _refused(_load(path, "load_map"), path, "MAX_LANE")


@pytest.mark.parametrize(
    ("shape", "fragment"), [((20_000, 2, 4), "MAX_TRACKS"), ((2, 30_000, 4), "MAX_STEPS")]
)
def test_track_counts_refused_from_the_header(tmp_path, shape, fragment):
    path = tmp_path / "tracks.npz"
    write_npz(path, _inline_scene(tmp_path) | {"states": np.zeros(shape, np.float32)})
    _refused(_load(path), path, "'states'", fragment)


# --- values out of their physical ranges --------------------------------------------------


def _scene_with(tmp_path: Path, **changes) -> Path:
    arrays = _inline_scene(tmp_path)
    arrays["states"] = arrays["states"].astype(np.float64)  # room for 1e300
    for key, change in changes.items():
        arrays[key] = change(arrays[key].copy())
    path = tmp_path / "values.npz"
    write_npz(path, arrays)
    return path


def _set(index, value):
    def change(array):
        array[index] = value
        return array

    return change


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"map_resolution": lambda a: np.array(1e-300)}, "resolution"),
        ({"map_resolution": lambda a: np.array(1e300)}, "resolution"),
        ({"map_resolution": lambda a: np.array(np.nan)}, "resolution"),
        ({"map_origin": _set(0, 1e300)}, "MAX_MAP_COORDINATE"),
        ({"map_origin": _set(1, np.inf)}, "origin"),
        ({"map_lane_widths": _set(0, 1e300)}, "MAX_LANE_WIDTH"),
        ({"map_lane_speed_limits": _set(0, 1e300)}, "MAX_SPEED_LIMIT"),
        ({"map_lane_points": _set((0, 0), 1e300)}, "MAX_MAP_COORDINATE"),
        ({"length": _set(0, 1e300)}, "length"),
        ({"width": _set(1, 0.0)}, "width"),
        ({"length": _set(2, np.nan)}, "length"),
        ({"dt": lambda a: np.array(1e-300)}, "dt"),
        ({"dt": lambda a: np.array(1e300)}, "dt"),
        ({"states": _set((0, 0, 0), 1e300)}, "position"),
        ({"states": _set((0, 0, 2), 1e300)}, "speed"),
        ({"states": _set((0, 0, 3), np.inf)}, "NaN or inf"),
    ],
)
def test_values_out_of_range_refused(tmp_path, changes, fragment):
    path = _scene_with(tmp_path, **changes)
    _refused(_load(path), path, fragment)


def test_stored_sdf_beyond_the_raster_refused(tmp_path):
    arrays = _arrays(MAP)
    sdf = np.where(arrays["drivable"], -1e30, 1e30).astype(np.float32)
    path = tmp_path / "sdf.npz"
    write_npz(path, arrays | {"sdf": sdf})
    _refused(_load(path, "load_map"), path, "sdf")


def test_far_but_valid_scene_gives_finite_observations(tmp_path):
    """A scene 990 km from the origin (the limits allow 1,000 km) loads, and 20 steps of
    the env observe only finite numbers; states at invalid steps read as 0."""
    scene = load_scenario(SCENE)
    shift = np.array([9.9e5 - scene.map.bounds[2], -9.9e5 - scene.map.bounds[1]])
    arrays = _arrays(save_scenario(scene, tmp_path / "near.npz"))
    arrays["map_origin"] = arrays["map_origin"] + shift
    arrays["map_lane_points"] = arrays["map_lane_points"] + shift
    states = arrays["states"].astype(np.float64)
    states[..., :2] += shift
    arrays["valid"][1:, -10:] = False  # the others' last second not observed ...
    states[~arrays["valid"]] = np.nan  # ... and NaN there: must not reach an observation
    arrays["states"] = states
    path = tmp_path / "far.npz"
    write_npz(path, arrays)
    call = f"""
import numpy as np, riskflow_env
scene = load_scenario({str(path)!r})
assert np.all(np.isfinite(scene.states)), "invalid steps must read as 0"
env = riskflow_env.parallel_env()
observations, _ = env.reset(seed=0, options={{"scenario": scene}})
for _ in range(20):
    assert all(np.all(np.isfinite(o)) for o in observations.values())
    if not env.agents:
        break
    observations, *_ = env.step({{a: env.action_space(a).sample() for a in env.agents}})
"""
    outcome = run_capped(SETUP, call)
    assert outcome.error is None, outcome


def _map_with_raster(tmp_path: Path, name: str, side: int, sdf: bool = False) -> Path:
    """A shipped map's lanes over a ``side`` x ``side`` raster, drivable in one band."""
    drivable = np.zeros((side, side), dtype=bool)
    drivable[side // 2 - 20 : side // 2 + 20] = True
    arrays = _arrays(MAP) | {"drivable": drivable}
    if sdf:  # any SDF that agrees in sign: compresses as well as the raster
        arrays["sdf"] = np.where(drivable, -0.25, 0.25).astype(np.float32)
    else:
        arrays.pop("sdf", None)
    path = tmp_path / name
    write_npz(path, arrays)
    return path


def test_large_raster_without_its_sdf_refused_from_the_header(tmp_path):
    """A 7,071 x 7,071 raster without an SDF (a 60 KB file) took about 45 s and 2.1 GB
    to load (its SDF computed): refused from the header, as a scene's inline map too."""
    path = _map_with_raster(tmp_path, "nosdf.npz", 7071)
    assert path.stat().st_size < 2**20
    _refused(_load(path, "load_map"), path, "MAX_SDF_PIXELS", "include_sdf=True")
    arrays = _inline_scene(tmp_path)
    arrays["map_drivable"] = np.zeros((7071, 7071), dtype=bool)
    arrays.pop("map_sdf", None)
    scene = tmp_path / "nosdf_scene.npz"
    write_npz(scene, arrays)
    _refused(_load(scene), scene, "MAX_SDF_PIXELS")


def test_rasters_within_the_sdf_budget_or_with_their_sdf_load(tmp_path):
    """At MAX_SDF_PIXELS the SDF is computed within the bounds; a larger raster that
    stores its SDF loads without computing one."""
    within = _map_with_raster(tmp_path, "within.npz", 2828)  # 7.997 M px
    _loaded(_load(within, "load_map"))
    stored = _map_with_raster(tmp_path, "stored.npz", 5000, sdf=True)
    _loaded(_load(stored, "load_map"))


def _loaded(outcome: Outcome) -> None:
    assert outcome.error is None, outcome
    assert_bounded(outcome)
