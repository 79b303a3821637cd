"""Hostile data pickles for the restricted unpickler: small files that expand, through
shared references or calls, to unbounded time or memory are refused, or loaded, within a
CPU-time bound and 500 MB; error messages stay short whatever the file holds.

Every file is built here, small, and read by ``load_data_pickle`` in a child process whose
address space is capped at 1.5 GB (:mod:`tests.riskflow_env.scenarios.hostile_files`).
The ScenarioNet scenes and folders are in test_hostile_scenarionet.py.
"""

from __future__ import annotations

import pickle
import struct

import pytest

from tests.riskflow_env.scenarios.hostile_files import loaded, refused, run, write

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

M61 = 2**61 - 1  # ints that differ by a multiple of it share a hash


# -- protocol-2 opcodes, for files pickle.dumps would not write ----------------------------


def put(i: int) -> bytes:
    return b"r" + struct.pack("<I", i)  # LONG_BINPUT


def get(i: int) -> bytes:
    return b"j" + struct.pack("<I", i)  # LONG_BINGET


def text(value: str) -> bytes:
    raw = value.encode()
    return b"X" + struct.pack("<I", len(raw)) + raw  # BINUNICODE


def call(module: str, name: str) -> bytes:
    return f"c{module}\n{name}\n".encode()  # GLOBAL


def ints(values: range) -> bytes:
    return b"".join(b"J" + struct.pack("<i", v) for v in values)  # BININT


def chain(levels: int) -> bytes:
    """``L[i] = [L[i-1], L[i-1]]`` in memo i: its repr is 2**levels long."""
    data = b"]" + put(0) + b"0"
    for i in range(1, levels):
        data += b"](" + get(i - 1) + get(i - 1) + b"e" + put(i) + b"0"
    return data


def repeated(count: int, item: bytes) -> bytes:
    """A list holding ``count`` times what ``item`` pushes."""
    return b"](" + item * count + b"e"


# -- the restricted unpickler --------------------------------------------------------------


def test_frozenset_of_one_shared_list_2000_times_refused(tmp_path):
    """0.5 MB: 2,000 frozensets of one 100,000-int list expanded to 3.9 GB."""
    body = call("builtins", "frozenset") + put(0) + b"](" + ints(range(100_000)) + b"e" + put(1)
    data = b"\x80\x02" + body + b"0" + repeated(2000, get(0) + get(1) + b"\x85R") + b"."
    refused(run(write(tmp_path, "frozensets.pkl", data)), "frozensets.pkl", "MAX_TOTAL_BYTES")


def test_encode_of_one_shared_string_3000_times_refused(tmp_path):
    """1 MiB: 3,000 encodings of one 1 MiB string made 3.1 GB."""
    body = call("_codecs", "encode") + put(0) + text("a" * 2**20) + put(1)
    item = get(0) + get(1) + text("latin1") + b"\x86R"
    data = b"\x80\x02" + body + b"0" + repeated(3000, item) + b"."
    refused(run(write(tmp_path, "encode.pkl", data)), "encode.pkl", "MAX_TOTAL_BYTES")


def test_list_shared_2000_times_refused_by_its_expansion(tmp_path):
    """One 100,000-item list referenced 2,000 times: 200 M elements, counted per reference."""
    data = pickle.dumps([list(range(100_000))] * 2000, protocol=4)
    refused(run(write(tmp_path, "shared.pkl", data)), "shared.pkl", "MAX_ELEMENTS")


ARRAY = b"cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R(K\x01"
F8 = b"cnumpy\ndtype\nX\x02\x00\x00\x00f8\x89\x88\x87R"


@pytest.mark.parametrize(
    ("name", "tail", "fragment"),
    [
        ("persistent_id", get(49) + b"Q.", "persistent id (a list of 2 items)"),
        ("dtype_spec", b"cnumpy\ndtype\n" + get(49) + b"\x85R.", "got a list of 2 items"),
        ("shape", ARRAY + get(49) + F8 + b"\x89C\x00tb.", "bad array shape a list of 2 items"),
        ("set_item", call("builtins", "set") + get(49) + b"\x85\x85R.", "type list"),
        ("call_args", call("builtins", "set") + get(49) + b"R.", "must be a tuple"),
    ],
)
def test_error_paths_do_not_format_a_shared_structure(tmp_path, name, tail, fragment):
    """Errors about a 50-level shared list (repr: 2**50 items) quote its type, not its repr
    (a persistent id, a dtype spec, a set item, call arguments)."""
    data = b"\x80\x02" + chain(50) + tail
    refused(run(write(tmp_path, f"{name}.pkl", data)), f"{name}.pkl", fragment)


@pytest.mark.parametrize(
    ("name", "data", "fragment"),
    [
        (
            "encoding",
            call("_codecs", "encode") + text("a") + text("x" * 10**6) + b"\x86R.",
            "(1000000 characters)",
        ),
        ("global", b"c" + b"m" * 10**6 + b"\nname\n.", "disallowed global"),
    ],
)
def test_error_paths_cut_long_strings(tmp_path, name, data, fragment):
    refused(run(write(tmp_path, f"{name}.pkl", b"\x80\x02" + data)), f"{name}.pkl", fragment)


def test_hash_collision_flood_refused(tmp_path):
    """100,000 int keys of one hash (k * (2**61 - 1)) took 135 s to insert: ints beyond
    64 bits, tuples and complex numbers are refused as keys."""
    keys = (k * M61 for k in range(1, 100_000))
    items = b"".join(b"\x8a" + bytes([12]) + k.to_bytes(12, "little") + b"N" for k in keys)
    path = write(tmp_path, "flood.pkl", b"\x80\x02}(" + items + b"u.")
    refused(run(path), "flood.pkl", "dict key or set item of type int")
    tuples = pickle.dumps({(k * M61,): None for k in range(1000)}, protocol=4)
    refused(run(write(tmp_path, "tuples.pkl", tuples)), "tuples.pkl", "type tuple")


def test_many_keys_sharing_low_bits_load_fast(tmp_path):
    """Keys a file may use cannot share a hash beyond a few: 100,000 ints that share their
    low 40 bits load at once."""
    data = pickle.dumps({k << 40: k for k in range(100_000)}, protocol=4)
    loaded(run(write(tmp_path, "keys.pkl", data), tail=" and None"))


@pytest.mark.parametrize(
    ("name", "data", "fragment"),
    [
        ("memo_index", b"N" + b"r\xff\xff\xff\xff" + b".", None),
        ("bytearray8_2e40", b"\x96" + struct.pack("<Q", 2**40) + b".", "MAX_ARRAY_BYTES"),
        ("bytearray8_short", b"\x96" + struct.pack("<Q", 60 * 2**20) + b"ab.", "past the end"),
        ("newobj", call("builtins", "set") + b")\x81.", "NEWOBJ"),
        ("ordered_dict_items", call("collections", "OrderedDict") + b"]\x85R.", "items"),
    ],
)
def test_opcodes_that_allocate_are_checked_first(tmp_path, name, data, fragment):
    """A memo index of 2**32 - 1 (the C unpickler allocated 8 bytes per index below it),
    BYTEARRAY8 sizes beyond the limits or the data, the object opcodes."""
    path = write(tmp_path, f"{name}.pkl", b"\x80\x04" + data)
    if fragment is None:
        loaded(run(path))
    else:
        refused(run(path), f"{name}.pkl", fragment)
