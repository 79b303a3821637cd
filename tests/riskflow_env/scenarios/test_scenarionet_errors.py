"""Malformed ScenarioNet files: every failure is one ValueError naming the file (issue 19).

The safe loader is documented to raise ``ValueError`` naming the file; a malformed
description used to escape as ``TypeError``, ``IndexError``, ``MemoryError`` or a
``ValueError`` from numpy that did not say which file was wrong.
"""

from __future__ import annotations

import copy
import importlib.util
import pickle
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from riskflow_env.scenarios import scenarionet
from riskflow_env.scenarios.safe_pickle import errors_name_the_file
from riskflow_env.scenarios.scenarionet import load_scenarionet

pytestmark = pytest.mark.reliability

_spec = importlib.util.spec_from_file_location(
    "_scenarionet_tests", Path(__file__).with_name("test_scenarionet.py")
)
_tests = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_tests)

# values that are wrong almost anywhere in a description
BAD_VALUES = {
    "str": "x",
    "int": 3,
    "none": None,
    "empty-dict": {},
    "3d-array": np.zeros((2, 3, 4)),
    "str-array": np.array(["a", "b"]),
}


def _key_paths(tree, prefix=()):
    """Every key path of the nested dicts of ``tree``."""
    for key, value in tree.items():
        yield (*prefix, key)
        if isinstance(value, dict):
            yield from _key_paths(value, (*prefix, key))


def _malformed():
    base = _tests._description()
    for path in _key_paths(base):
        for name, value in BAD_VALUES.items():
            description = copy.deepcopy(base)
            parent = description
            for key in path[:-1]:
                parent = parent[key]
            parent[path[-1]] = value
            yield "/".join(map(str, path)) + "=" + name, description


def test_malformed_descriptions_raise_value_error_naming_the_file(tmp_path):
    escaped = []
    count = 0
    for label, description in _malformed():
        path = tmp_path / "scene.pkl"
        path.write_bytes(pickle.dumps(description))
        count += 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                load_scenarionet(path)
        except ValueError as err:
            if str(path) not in str(err):
                escaped.append(f"{label}: ValueError without the file name: {err}")
        except Exception as err:
            escaped.append(f"{label}: {type(err).__name__}: {err}")
    assert count > 200
    assert not escaped, "\n".join(escaped[:20])


@pytest.mark.parametrize("error", [MemoryError, IndexError, LookupError, KeyError, TypeError])
def test_any_failure_inside_the_loader_becomes_value_error(error, tmp_path, monkeypatch):
    path = tmp_path / "scene.pkl"
    path.write_bytes(pickle.dumps(_tests._description()))

    def fail(*args, **kwargs):
        raise error("deep inside")

    monkeypatch.setattr(scenarionet, "build_map", fail)
    message = rf"{re.escape(str(path))}: .*{error.__name__}: .*deep inside"
    with pytest.raises(ValueError, match=message):
        load_scenarionet(path)


@pytest.mark.parametrize("error", [KeyboardInterrupt, SystemExit, GeneratorExit])
def test_interrupts_are_not_swallowed(error, tmp_path, monkeypatch):
    path = tmp_path / "scene.pkl"
    path.write_bytes(pickle.dumps(_tests._description()))

    def interrupt(*args, **kwargs):
        raise error()

    monkeypatch.setattr(scenarionet, "build_map", interrupt)
    with pytest.raises(error):
        load_scenarionet(path)


def test_value_error_that_names_the_file_passes_unchanged():
    with pytest.raises(ValueError, match=r"^a\.pkl: precise reason$"):
        with errors_name_the_file("a.pkl"):
            raise ValueError("a.pkl: precise reason")
    with pytest.raises(ValueError, match=r"^a\.pkl: not a readable data pickle \(vague\)$"):
        with errors_name_the_file("a.pkl"):
            raise ValueError("vague")


def _complex_cases():
    """(label, description) with one array the loader reads made complex, per source."""
    from tests.riskflow_env.scenarios.scenarionet_sources import SOURCES, description

    for source in SOURCES:
        base = description(source)
        sdc = base["metadata"]["sdc_id"]
        lane = next(k for k, f in base["map_features"].items() if f["type"].startswith("LANE"))
        read = ("position", "heading", "velocity", "valid", "length", "width")  # not height
        paths = [("tracks", sdc, "state", key) for key in read]
        paths += [("map_features", lane, key) for key in ("polyline", "polygon", "width")]
        paths += [("metadata", "ts")]
        for path in paths:
            description_ = copy.deepcopy(base)
            parent = description_
            for key in path[:-1]:
                parent = parent[key]
            if path[-1] not in parent or np.asarray(parent[path[-1]]).dtype.kind not in "biuf":
                continue
            parent[path[-1]] = np.asarray(parent[path[-1]]).astype(np.complex128) + 1j
            yield f"{source}:" + "/".join(map(str, path)), description_


@pytest.mark.parametrize(("label", "description"), list(_complex_cases()))
def test_complex_numbers_are_refused_not_cast(label, description, tmp_path):
    """Issue 19: complex arrays were cast to float with a ComplexWarning, dropping the
    imaginary part; now a ValueError names the file and the field."""
    path = tmp_path / "scene.pkl"
    path.write_bytes(pickle.dumps(description))
    field = label.split("/")[-1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way
        with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: .*{field}.* complex"):
            load_scenarionet(path)


@pytest.mark.parametrize("key", ["length", "width"])
@pytest.mark.parametrize("bad", [-4.0, -np.inf, np.inf])
def test_negative_or_infinite_sizes_are_refused(key, bad, tmp_path):
    """A negative length was dropped like a missing one and the track got another size;
    now it is an error naming the file, the track and the field."""
    description = _tests._description()
    description["tracks"]["car"]["state"][key][4:] = bad
    path = tmp_path / "scene.pkl"
    path.write_bytes(pickle.dumps(description))
    message = rf"{re.escape(str(path))}: track 'car' {key} must be > 0 m .* got {bad:g}"
    with pytest.raises(ValueError, match=message):
        load_scenarionet(path)


def test_missing_sizes_are_repaired_and_invalid_steps_ignored(tmp_path):
    """0 and NaN mean "not given": the median of the given sizes, else 4.5 x 2.0 m; a size
    at an invalid step (Waymo writes -1 there) is not read."""
    description = _tests._description()
    car, ego = description["tracks"]["car"]["state"], description["tracks"]["ego"]["state"]
    car["length"][:5], car["length"][5:8] = 0.0, np.nan  # some steps give none
    car["length"][-3:] = -1.0  # the car's invalid steps
    car["width"] = car["width"].reshape(-1)  # (T,) as the Waymo converter writes them
    car["width"][-3:] = -1.0
    ego["length"][:], ego["width"][:] = np.nan, 0.0  # no size at all
    scenario = scenarionet.scenario_from_description(description)
    np.testing.assert_allclose(scenario.length, [4.5, 4.0])
    np.testing.assert_allclose(scenario.width, [2.0, 2.0])
