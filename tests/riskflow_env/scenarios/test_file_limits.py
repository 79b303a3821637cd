"""Small files that declare huge sizes are refused before allocation (issue 19 item 2)."""

import importlib.util
import pickle
import resource
import zipfile
from pathlib import Path

import numpy as np
import pytest

from riskflow_env.scenarios import _npz
from riskflow_env.scenarios.io import load_map, load_scenario
from riskflow_env.scenarios.safe_pickle import loads_data_pickle
from riskflow_env.scenarios.scenarionet import load_scenarionet

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

_spec = importlib.util.spec_from_file_location(
    "_scenarionet_tests", Path(__file__).with_name("test_scenarionet.py")
)
_tests = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_tests)


def _peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def test_bytearray_3e9_pickle_refused_without_allocating():
    data = b"\x80\x02c__builtin__\nbytearray\n\x8a\x05\x00^\xd0\xb2\x00\x85R."
    assert len(data) <= 40
    before = _peak_mb()
    with pytest.raises(ValueError, match="MAX_ARRAY_BYTES"):
        loads_data_pickle(data, source="small.pkl")
    assert _peak_mb() - before < 500


def test_scenarionet_huge_timestamps_refused(tmp_path):
    description = _tests._description(steps=91, rate=0.1)
    description["metadata"]["ts"] = np.arange(91) * 1e5
    path = tmp_path / "stretched.pkl"
    path.write_bytes(pickle.dumps(description))
    with pytest.raises(ValueError, match=r"stretched\.pkl.*MAX_STEPS"):
        load_scenarionet(path)


@pytest.mark.parametrize("rate", [0.0, -1.0, float("nan")])
def test_scenarionet_bad_sample_rate_refused(tmp_path, rate):
    description = _tests._description()
    del description["metadata"]["ts"]
    description["metadata"]["sample_rate"] = rate
    path = tmp_path / "rate.pkl"
    path.write_bytes(pickle.dumps(description))
    with pytest.raises(ValueError, match="rate.pkl"):
        load_scenarionet(path)


def _npz_with_declared_shape(path, shape, dtype="<f4"):
    """A tiny .npz whose member header declares ``shape`` (body left out)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open("raster.npy", "w") as handle:
            np.lib.format.write_array_header_1_0(
                handle, {"descr": dtype, "fortran_order": False, "shape": shape}
            )
            handle.write(b"\x00" * 1024)
        with archive.open("schema.npy", "w") as handle:
            np.lib.format.write_array(handle, np.array("riskflow_map"))


@pytest.mark.parametrize("loader", [load_map, load_scenario])
def test_npz_huge_raster_refused_from_header(tmp_path, loader):
    path = tmp_path / "huge.npz"
    _npz_with_declared_shape(path, (12_000, 12_000))
    assert path.stat().st_size < 200_000
    before = _peak_mb()
    with pytest.raises(_npz.ScenarioFormatError, match=r"huge\.npz.*MAX_MEMBER_ELEMENTS"):
        loader(path)
    assert _peak_mb() - before < 200


def test_npz_total_bytes_limit(tmp_path, monkeypatch):
    monkeypatch.setattr(_npz, "MAX_FILE_ARRAY_BYTES", 1000)
    path = tmp_path / "many.npz"
    _npz_with_declared_shape(path, (1000,))
    with pytest.raises(_npz.ScenarioFormatError, match="MAX_FILE_ARRAY_BYTES"):
        load_map(path)
