"""The restricted unpickler reads the containers ScenarioNet's converters write
(``collections.defaultdict`` with a builtin factory, ``collections.OrderedDict``) and
refuses every global that can call code, each tested on its own."""

from __future__ import annotations

import collections
import pickle

import pytest

from riskflow_env.scenarios.safe_pickle import ALLOWED_GLOBALS, loads_data_pickle


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
@pytest.mark.parametrize("factory", [int, list, dict, float, str, tuple, bool, set, None])
def test_defaultdict_with_a_builtin_factory_loads(protocol, factory):
    data = collections.defaultdict(factory)
    if factory is not None:
        data["VEHICLE"] = factory()
    loaded = loads_data_pickle(pickle.dumps({"number_summary": data}, protocol=protocol))
    counts = loaded["number_summary"]
    assert isinstance(counts, collections.defaultdict) and counts.default_factory is factory
    assert dict(counts) == dict(data)


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_ordered_dict_and_nested_defaultdict_load(protocol):
    data = collections.OrderedDict(b=collections.defaultdict(list, {"x": [1, 2]}), a=(1, {2}))
    loaded = loads_data_pickle(pickle.dumps(data, protocol=protocol))
    assert type(loaded) is collections.OrderedDict and list(loaded) == ["b", "a"]
    assert loaded["b"]["x"] == [1, 2] and loaded["b"]["new"] == []


def _call(module: str, name: str, args: bytes = b"") -> bytes:
    """Protocol-2 pickle calling ``module.name(*args)``: GLOBAL, MARK, args, TUPLE, REDUCE."""
    return b"\x80\x02c" + module.encode() + b"\n" + name.encode() + b"\n(" + args + b"tR."


TEXT = b"X\x04\x00\x00\x00echo"

REFUSED = [
    ("os", "system"),
    ("posix", "system"),
    ("nt", "system"),
    ("subprocess", "Popen"),
    ("subprocess", "check_output"),
    ("builtins", "eval"),
    ("builtins", "exec"),
    ("builtins", "compile"),
    ("builtins", "open"),
    ("builtins", "getattr"),
    ("builtins", "setattr"),
    ("builtins", "__import__"),
    ("builtins", "globals"),
    ("builtins", "type"),
    ("builtins", "object"),
    ("builtins", "print"),
    ("builtins", "input"),
    ("builtins", "breakpoint"),
    ("__builtin__", "eval"),
    ("__builtin__", "apply"),
    ("copyreg", "_reconstructor"),
    ("copy_reg", "_reconstructor"),
    ("functools", "partial"),
    ("functools", "reduce"),
    ("operator", "attrgetter"),
    ("operator", "methodcaller"),
    ("operator", "itemgetter"),
    ("collections", "namedtuple"),
    ("collections", "Counter"),
    ("collections", "deque"),
    ("collections", "ChainMap"),
    ("collections", "UserDict"),
    ("pickle", "loads"),
    ("_pickle", "loads"),
    ("marshal", "loads"),
    ("importlib", "import_module"),
    ("runpy", "run_path"),
    ("shutil", "rmtree"),
    ("numpy", "load"),
    ("numpy", "fromfile"),
    ("numpy", "frombuffer"),
    ("numpy.lib.npyio", "load"),
    ("numpy.core.multiarray", "_reconstruct_from_buffer"),
    ("numpy.ctypeslib", "as_array"),
    ("ctypes", "cast"),
    ("torch", "load"),
    ("pandas", "read_pickle"),
    ("codecs", "open"),
    ("_codecs", "decode"),
    ("types", "FunctionType"),
    ("types", "CodeType"),
    ("sys", "exit"),
]


@pytest.mark.parametrize(("module", "name"), REFUSED, ids=[f"{m}.{n}" for m, n in REFUSED])
def test_each_code_calling_global_is_refused(module, name):
    assert (module, name) not in ALLOWED_GLOBALS
    with pytest.raises(ValueError, match=rf"disallowed global '{module}\.{name}'"):
        loads_data_pickle(_call(module, name, TEXT), source="evil.pkl")


FACTORY_CALLS = ["list", "int", "float", "dict", "str", "tuple", "bool"]


@pytest.mark.parametrize("name", FACTORY_CALLS)
def test_builtin_factories_cannot_be_called_from_a_file(name):
    with pytest.raises(ValueError, match=rf"evil.pkl: .*calling builtins\.{name} is refused"):
        loads_data_pickle(_call("builtins", name, TEXT), source="evil.pkl")


@pytest.mark.parametrize("name", FACTORY_CALLS)
def test_a_bare_builtin_type_is_refused(name):
    payload = b"\x80\x02}X\x01\x00\x00\x00kcbuiltins\n" + name.encode() + b"\ns."
    with pytest.raises(ValueError, match=rf"bare builtins\.{name} reference"):
        loads_data_pickle(payload, source="evil.pkl")


@pytest.mark.parametrize(
    ("factory", "message"),
    [
        (b"c_codecs\nencode\n", "factory function is refused"),
        (b"cnumpy\ndtype\n", "factory type is refused"),
        (b"cbuiltins\nbytearray\n", "factory function is refused"),
        (b"ccollections\nOrderedDict\n", "factory type is refused"),
        (b"ccollections\ndefaultdict\n", "factory function is refused"),
        (b"K\x07", "factory int is refused"),
    ],
)
def test_defaultdict_factory_other_than_a_builtin_type_is_refused(factory, message):
    payload = b"\x80\x02ccollections\ndefaultdict\n" + factory + b"\x85R."
    with pytest.raises(ValueError, match=f"evil.pkl: .*{message}"):
        loads_data_pickle(payload, source="evil.pkl")


def test_defaultdict_with_items_in_its_call_is_refused():
    payload = b"\x80\x02ccollections\ndefaultdict\nN}\x86R."
    with pytest.raises(ValueError, match="initial items"):
        loads_data_pickle(payload, source="evil.pkl")


def test_a_type_reference_as_a_dict_key_is_refused():
    payload = b"\x80\x02}cbuiltins\nlist\nK\x01s."
    with pytest.raises(ValueError, match="dict key"):
        loads_data_pickle(payload, source="evil.pkl")


@pytest.mark.parametrize("kind", [list, tuple, dict])
def test_nesting_limit_is_exact_for_every_container(kind):
    """Items nested MAX_DEPTH deep load; one level more is refused (leaves are passed over
    without a call, containers holding them are still checked)."""
    from riskflow_env.scenarios.safe_pickle import MAX_DEPTH

    def nest(levels):
        value = "leaf"
        for _ in range(levels):
            value = {"k": value} if kind is dict else kind([value])
        return value

    assert loads_data_pickle(pickle.dumps(nest(MAX_DEPTH))) == nest(MAX_DEPTH)
    with pytest.raises(ValueError, match="nested deeper than MAX_DEPTH"):
        loads_data_pickle(pickle.dumps(nest(MAX_DEPTH + 1)))
    shared = [nest(MAX_DEPTH - 1)] * 3  # one list seen three times: still MAX_DEPTH deep
    assert loads_data_pickle(pickle.dumps(shared)) == shared
