"""Hostile data pickles (issue 19): nothing reads memory, nothing runs, nothing hangs."""

import collections
import pickle
import struct
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from riskflow_env.scenarios import safe_pickle
from riskflow_env.scenarios.safe_pickle import load_data_pickle, loads_data_pickle

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md


def i8(value):
    return b"\x8a\x08" + struct.pack("<q", value)


def ndarray_offset_pickle(offset, count=256):
    return (
        b"\x80\x02cnumpy\nndarray\n("
        + i8(count)
        + b"\x85X\x02\x00\x00\x00u1C\x10"
        + b"A" * 16
        + i8(offset)
        + b"tR."
    )


def bytearray_buffer_pickle(offset):
    # ndarray(shape, dtype, bytearray buffer, offset): the write-before-the-buffer variant
    return (
        b"\x80\x02cnumpy\nndarray\n("
        + i8(64)
        + b"\x85X\x02\x00\x00\x00u1c__builtin__\nbytearray\n"
        + i8(16)
        + b"\x85R"
        + i8(offset)
        + b"tR."
    )


HOSTILE = {
    "ndarray_negative_offset": ndarray_offset_pickle(-4096),
    "ndarray_far_offset": ndarray_offset_pickle(-(2**40)),
    "ndarray_bytearray_buffer": bytearray_buffer_pickle(-64),
    "bytearray_3e9": b"\x80\x02c__builtin__\nbytearray\n" + i8(3_000_000_000) + b"\x85R.",
    "bytes_3e9": b"\x80\x03cbuiltins\nbytes\n" + i8(3_000_000_000) + b"\x85R.",
    "os_system": b"cos\nsystem\n(S'touch /tmp/riskflow_hostile_marker'\ntR.",
    "reconstruct_huge": pickle.dumps(np.zeros(4, np.float64))[:0]
    + b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R"
    + b"(K\x01"
    + i8(2**20)
    + i8(2**20)
    + b"\x86cnumpy\ndtype\nX\x02\x00\x00\x00f8\x89\x88\x87R"
    + b"(K\x03X\x01\x00\x00\x00<NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb\x89C\x00tb.",
    "object_dtype": b"\x80\x02cnumpy\ndtype\nX\x02\x00\x00\x00O8\x89\x88\x87R.",
    "codecs_lookup": b"\x80\x02c_codecs\nencode\nX\x01\x00\x00\x00aX\x04\x00\x00\x00nope\x86R.",
    "truncated": pickle.dumps({"a": np.arange(100)})[:-20],
    "deep_nesting": b"\x80\x02" + b"]" * 100_000 + b"a" * 99_999 + b".",
    "empty": b"",
}


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_hostile_pickle_raises_value_error_naming_source(name, tmp_path):
    with pytest.raises(ValueError, match="hostile.pkl"):
        loads_data_pickle(HOSTILE[name], source="hostile.pkl")
    path = tmp_path / f"{name}.pkl"
    path.write_bytes(HOSTILE[name])
    with pytest.raises(ValueError, match=name):
        load_data_pickle(path)


def test_issue_reproduction_ndarray_offset_refused():
    with pytest.raises(ValueError, match="numpy.ndarray"):
        loads_data_pickle(ndarray_offset_pickle(-4096))


def test_far_offsets_do_not_crash_the_interpreter():
    code = textwrap.dedent(
        """
        import struct, sys
        from riskflow_env.scenarios.safe_pickle import loads_data_pickle
        i8 = lambda v: b"\\x8a\\x08" + struct.pack("<q", v)
        for offset in (-4096, -2**20, -2**40, 2**40, 2**62):
            data = (b"\\x80\\x02cnumpy\\nndarray\\n(" + i8(256)
                    + b"\\x85X\\x02\\x00\\x00\\x00u1C\\x10"
                    + b"A" * 16 + i8(offset) + b"tR.")
            try:
                loads_data_pickle(data)
            except ValueError:
                continue
            sys.exit(3)
        print("ok")
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "ok" in result.stdout


def test_no_marker_file_written(tmp_path):
    marker = tmp_path / "marker"
    data = f"cos\nsystem\n(S'touch {marker}'\ntR.".encode()
    with pytest.raises(ValueError):
        loads_data_pickle(data)
    assert not marker.exists()


def test_file_size_limit(tmp_path, monkeypatch):
    monkeypatch.setattr(safe_pickle, "MAX_FILE_BYTES", 10)
    path = tmp_path / "big.pkl"
    path.write_bytes(pickle.dumps(list(range(100))))
    with pytest.raises(ValueError, match="MAX_FILE_BYTES"):
        load_data_pickle(path)


def test_file_size_limit_when_read_for_the_map_cache(tmp_path, monkeypatch):
    """``load_scenarionet(..., map_cache=...)`` reads the bytes itself (to hash them): the
    same limit, one bounded read, the file named."""
    from riskflow_env.scenarios.map_cache import MapCache
    from riskflow_env.scenarios.scenarionet import load_scenarionet

    monkeypatch.setattr(safe_pickle, "MAX_FILE_BYTES", 10)
    path = tmp_path / "big.pkl"
    path.write_bytes(pickle.dumps(list(range(100))))
    with pytest.raises(ValueError, match=rf"{path}: .*MAX_FILE_BYTES"):
        safe_pickle.read_data_file(path)
    with pytest.raises(ValueError, match=rf"{path}: .*MAX_FILE_BYTES"):
        load_scenarionet(path, map_cache=MapCache(tmp_path / "maps"))
    assert not (tmp_path / "maps").exists()


def test_total_bytes_limit(monkeypatch):
    monkeypatch.setattr(safe_pickle, "MAX_TOTAL_BYTES", 1000)
    data = pickle.dumps([np.zeros(100), np.zeros(100)], protocol=2)
    with pytest.raises(ValueError, match="MAX_TOTAL_BYTES"):
        loads_data_pickle(data)


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_plain_arrays_still_load(protocol):
    data = {
        "f": np.arange(6.0).reshape(2, 3),
        "fortran": np.asfortranarray(np.arange(6, dtype=np.int32).reshape(2, 3)),
        "s": np.array(["ab", "c"]),
        "b": np.array([True, False]),
        "scalar": np.float32(2.5),
        "dtype": np.dtype(">i4"),
        "raw": bytearray(b"xy"),
    }
    loaded = loads_data_pickle(pickle.dumps(data, protocol=protocol))
    for key in ("f", "fortran", "s", "b"):
        assert type(loaded[key]) is np.ndarray
        np.testing.assert_array_equal(loaded[key], data[key])
    assert loaded["fortran"].flags.f_contiguous
    assert loaded["scalar"] == np.float32(2.5) and loaded["dtype"] == np.dtype(">i4")
    assert loaded["raw"] == bytearray(b"xy")


def test_object_arrays_refused():
    data = pickle.dumps(np.array([1, "a"], dtype=object), protocol=2)
    with pytest.raises(ValueError, match="refused"):
        loads_data_pickle(data)


FUZZ = """
import pickle, random, resource, sys
import numpy as np
resource.setrlimit(resource.RLIMIT_AS, (4 * 2**30, 4 * 2**30))
from riskflow_env.scenarios.safe_pickle import loads_data_pickle

rng = random.Random(int(sys.argv[1]))
seeds = [
    pickle.dumps({"a": np.arange(12.0).reshape(3, 4), "b": [np.int32(3), "x", b"yz"]}, protocol=p)
    for p in range(pickle.HIGHEST_PROTOCOL + 1)
]
seeds.append(pickle.dumps({"ts": np.arange(5) * 0.1, "ba": bytearray(b"abc")}, protocol=2))
bad = 0
for _ in range(int(sys.argv[2])):
    data = bytearray(rng.choice(seeds))
    for _ in range(rng.randint(1, 4)):
        op, at = rng.random(), rng.randrange(len(data))
        if op < 0.5:
            data[at] = rng.randrange(256)
        elif op < 0.7:
            del data[at]
        elif op < 0.9:
            data.insert(at, rng.randrange(256))
        else:
            data = data[:at]
        if not data:
            data = bytearray(b"(")
    try:
        loads_data_pickle(bytes(data), source="fuzz.pkl")
    except ValueError as error:
        assert "fuzz.pkl" in str(error), error
    except BaseException as error:
        print("UNEXPECTED", type(error).__name__, error, bytes(data))
        bad += 1
print("bad", bad)
"""


def test_mutated_pickles_raise_only_value_error():
    result = subprocess.run(
        [sys.executable, "-c", FUZZ, "0", "3000"], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "bad 0" in result.stdout, result.stdout[-3000:]


def shared_chain_pickle(levels, tail=b""):
    """``L[i] = [L[i-1], L[i-1]]``: ~19 bytes a level, 2**levels paths to the bottom."""
    memo = lambda i: struct.pack("<I", i)  # noqa: E731
    data = b"\x80\x02]r" + memo(0) + b"0"
    for i in range(1, levels):
        data += b"](j" + memo(i - 1) + b"j" + memo(i - 1) + b"er" + memo(i) + b"0"
    return data + (tail or b"j" + memo(levels - 1) + b".")


def test_shared_references_do_not_hang():
    """A 1 KB file sharing one list 2**60 times over loaded for days (each path walked);
    it expands to 2**61 elements and is refused at once (MAX_ELEMENTS), while a chain
    that expands within the limit loads with its sharing kept."""
    data = shared_chain_pickle(60)
    assert len(data) < 1200
    start = time.perf_counter()
    with pytest.raises(ValueError, match="MAX_ELEMENTS"):
        loads_data_pickle(data)
    assert time.perf_counter() - start < 5.0
    loaded = loads_data_pickle(shared_chain_pickle(12))
    assert loaded[0] is loaded[1]  # sharing kept, not expanded


def test_str_of_a_shared_structure_refused():
    """builtins.str is not a global pickle writes; str() of the chain above is exponential."""
    levels = 40
    memo = struct.pack("<I", levels - 1)
    data = shared_chain_pickle(levels, tail=b"cbuiltins\nstr\nj" + memo + b"\x85R.")
    with pytest.raises(ValueError, match="builtins.str"):
        loads_data_pickle(data)


def test_cycles_load():
    value = [1]
    value.append(value)
    loaded = loads_data_pickle(pickle.dumps({"a": value, "b": (value, np.arange(3))}))
    assert loaded["a"][1] is loaded["a"] and loaded["b"][0] is loaded["a"]
    assert type(loaded["b"][1]) is np.ndarray


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_plain_python_values_still_load(protocol):
    data = collections.OrderedDict(
        s={1, 2}, fs=frozenset({"a"}), c=1 + 2j, b=b"\x00\xff", empty=b"", t=(True, None),
        big=2**100, f=-0.5, u="\u00e9", n=[[], {}], ba=bytearray(b"z"),
    )  # fmt: skip
    assert loads_data_pickle(pickle.dumps(data, protocol=protocol)) == data


def test_load_scenarionet_refuses_the_offset_pickle(tmp_path):
    from riskflow_env.scenarios.scenarionet import load_scenarionet

    path = tmp_path / "scene.pkl"
    path.write_bytes(ndarray_offset_pickle(-4096))
    with pytest.raises(ValueError, match=r"scene\.pkl.*numpy\.ndarray"):
        load_scenarionet(path)
