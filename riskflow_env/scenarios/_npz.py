"""Low-level ``.npz`` helpers of the scenario format: deterministic writes, schema checks.

Reading is checked in two passes. :func:`check_npz_sizes` reads only the zip directory and
each member's ``.npy`` header (a few hundred bytes each): member names, compression, dtype,
shape, and the compressed and uncompressed sizes the zip declares are checked against the
limits below before any array data is decompressed, so a small file cannot make the loader
decompress or allocate more than the limits allow. Then :func:`read_npz` loads the arrays
(``allow_pickle=False``); a member decompresses to at most the size its zip entry declares.
"""

from __future__ import annotations

import re
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from riskflow_env.atomic_files import atomic_path

VERSION = 1
MAX_MEMBER_ELEMENTS = 50_000_000  # [-] largest array in a scenario / map file (= maps.MAX_PIXELS)
MAX_MEMBER_BYTES = 256 * 2**20  # [bytes] one array (a 50 Mpx float32 SDF is 200 MB)
MAX_FILE_ARRAY_BYTES = 512 * 2**20  # [bytes] all arrays of one scenario / map file together
MAX_MEMBERS = 64  # [-] members of one archive (a scene with an inline map has 33 at most)
MAX_DIRECTORY_BYTES = 64 * 2**10  # [bytes] the zip's central directory (about 100 per member)
MAX_DIMS = 4  # [-] dimensions of one array
EXTRA_PREFIX = "extra_"  # members an application adds (header-checked, then ignored)
MAX_STRING_CHARS = 1024  # [chars] longest string of a str array (names, ids, paths)
_MAX_HEADER_BYTES = 10_016  # [bytes] largest .npy header numpy reads (magic and length included)
_DTYPE_KINDS = "biufU"  # bool, int, uint, float, str: what the formats store
_MEMBER_NAME = re.compile(r"[A-Za-z0-9_]{1,64}\.npy")
_END_OF_DIRECTORY = b"PK\x05\x06"
_ZIP64_LOCATOR = b"PK\x06\x07"


class ScenarioFormatError(ValueError):
    """A scenario or map file that cannot be read: the message names the file and why."""


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez_compressed`` with fixed zip timestamps, written atomically
    (:func:`riskflow_env.atomic_files.atomic_path`)."""
    with atomic_path(path) as temporary:
        with zipfile.ZipFile(temporary, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            for key, value in arrays.items():
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                with archive.open(info, "w", force_zip64=True) as handle:
                    np.lib.format.write_array(handle, np.asanyarray(value), allow_pickle=False)


class Member(NamedTuple):
    """An array as its ``.npy`` header declares it (nothing of it loaded)."""

    shape: tuple[int, ...]
    dtype: np.dtype

    @property
    def ndim(self) -> int:
        return len(self.shape)


def check_npz_sizes(path: Path) -> dict[str, Member]:
    """The arrays ``path`` declares, by key, read from its zip directory and ``.npy``
    headers alone, before any array data is decompressed; ScenarioFormatError naming the
    file and the member unless:

    * the directory is at most :data:`MAX_DIRECTORY_BYTES` and lists at most
      :data:`MAX_MEMBERS` members, each named ``<key>.npy`` once, stored or deflated, not
      encrypted;
    * each header declares a bool, int, float or str dtype (strings of at most
      :data:`MAX_STRING_CHARS`), at most :data:`MAX_DIMS` dimensions and
      :data:`MAX_MEMBER_ELEMENTS` elements, and exactly the bytes its zip entry holds;
    * no member holds over :data:`MAX_MEMBER_BYTES`, and all together at most
      :data:`MAX_FILE_ARRAY_BYTES` (from the zip's uncompressed sizes).
    """
    try:
        _check_directory(path)
        members: dict[str, Member] = {}
        with zipfile.ZipFile(path) as archive:
            entries = archive.infolist()
            if len(entries) > MAX_MEMBERS:
                raise ScenarioFormatError(
                    f"{path}: {len(entries)} zip members exceed the limit MAX_MEMBERS = "
                    f"{MAX_MEMBERS}"
                )
            seen: set[str] = set()
            keys = [_check_entry(path, info, seen) for info in entries]
            total = sum(info.file_size for info in entries)
            if total > MAX_FILE_ARRAY_BYTES:
                raise ScenarioFormatError(
                    f"{path}: its members decompress to {total} bytes, over the limit "
                    f"MAX_FILE_ARRAY_BYTES = {MAX_FILE_ARRAY_BYTES}"
                )
            for key, info in zip(keys, entries, strict=True):
                with archive.open(info) as handle:
                    members[key] = _read_header(path, key, handle, info.file_size)
    except ScenarioFormatError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, RuntimeError) as error:
        raise ScenarioFormatError(f"{path}: not a readable .npz file ({_short(error)})") from None
    return members


def _check_directory(path: Path) -> None:
    """The size of the zip's central directory, from its end record (read as ``zipfile``
    reads it), before ``zipfile`` parses the directory into one object per member."""
    end_record = getattr(zipfile, "_EndRecData", None)  # CPython's reader of that record
    if end_record is None:
        return
    with open(path, "rb") as handle:
        record = end_record(handle)
    if not record:
        raise ValueError("no zip end-of-directory record")
    size, count = record[zipfile._ECD_SIZE], record[zipfile._ECD_ENTRIES_TOTAL]
    if size > MAX_DIRECTORY_BYTES or count > MAX_MEMBERS:
        raise ScenarioFormatError(
            f"{path}: a zip directory of {size} bytes listing {count} members exceeds the limits "
            f"MAX_DIRECTORY_BYTES = {MAX_DIRECTORY_BYTES}, MAX_MEMBERS = {MAX_MEMBERS}"
        )


def _check_entry(path: Path, info: zipfile.ZipInfo, seen: set[str]) -> str:
    """The key of zip entry ``info`` (added to ``seen``, the keys before it) after checking
    its name, compression and size."""
    name = info.filename
    if not _MEMBER_NAME.fullmatch(name):
        raise ScenarioFormatError(
            f"{path}: unexpected zip member {_short(name)!r} (expected <key>.npy, the key "
            "made of letters, digits and underscores)"
        )
    key = name[:-4]
    if key in seen:
        raise ScenarioFormatError(f"{path}: zip member {name!r} appears twice")
    seen.add(key)
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED) or info.flag_bits & 1:
        raise ScenarioFormatError(
            f"{path}: member {name!r} is encrypted or compressed with method "
            f"{info.compress_type} (expected stored or deflated)"
        )
    if info.file_size > MAX_MEMBER_BYTES + _MAX_HEADER_BYTES:
        raise ScenarioFormatError(
            f"{path}: member {name!r} decompresses to {info.file_size} bytes, over the limit "
            f"MAX_MEMBER_BYTES = {MAX_MEMBER_BYTES}"
        )
    return key


def _read_header(path: Path, key: str, handle, file_size: int) -> Member:
    """The ``.npy`` header of member ``key`` (open as ``handle``), checked against the
    limits and against the ``file_size`` its zip entry declares."""
    version = np.lib.format.read_magic(handle)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(handle)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(handle)
    else:
        raise ValueError(f"member {key!r}: unsupported .npy version {version}")
    where = f"{path}: member {key!r}"
    if dtype.kind not in _DTYPE_KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise ScenarioFormatError(
            f"{where} has dtype {_short(dtype)}, expected bool, int, float or str"
        )
    if dtype.kind == "U" and dtype.itemsize // 4 > MAX_STRING_CHARS:
        raise ScenarioFormatError(
            f"{where} holds strings of {dtype.itemsize // 4} characters, over the limit "
            f"MAX_STRING_CHARS = {MAX_STRING_CHARS}"
        )
    if len(shape) > MAX_DIMS:
        raise ScenarioFormatError(
            f"{where} has {len(shape)} dimensions, over MAX_DIMS = {MAX_DIMS}"
        )
    count = 1
    for dim in shape:
        count *= int(dim)
    if count > MAX_MEMBER_ELEMENTS:
        raise ScenarioFormatError(
            f"{where}: array of shape {shape} exceeds the limit "
            f"MAX_MEMBER_ELEMENTS = {MAX_MEMBER_ELEMENTS}"
        )
    declared = count * dtype.itemsize
    if declared > MAX_MEMBER_BYTES:
        raise ScenarioFormatError(
            f"{where}: array of shape {shape}, dtype {dtype} ({declared} bytes) exceeds the limit "
            f"MAX_MEMBER_BYTES = {MAX_MEMBER_BYTES}"
        )
    if handle.tell() + declared != file_size:
        raise ScenarioFormatError(
            f"{where}: its header declares {declared} bytes of data, its zip entry holds "
            f"{file_size - handle.tell()}"
        )
    return Member(tuple(int(dim) for dim in shape), dtype)


def _short(value: object, limit: int = 200) -> str:
    """``str(value)``, cut to ``limit`` characters (messages never quote much of a file)."""
    text = str(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def read_npz(
    path: Path, schema: str, check: Callable[[Path, dict[str, Member]], None] | None = None
) -> dict[str, np.ndarray]:
    """All arrays of ``path``, loaded after :func:`check_npz_sizes` and ``check(path,
    members)`` (e.g. :func:`check_arrays` against the format) have accepted what its
    headers declare, then its ``schema`` and ``version`` checked."""
    if not path.is_file():
        raise FileNotFoundError(f"scenario file {path} not found")
    members = check_npz_sizes(path)
    if check is not None:
        check(path, members)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, RuntimeError) as error:
        raise ScenarioFormatError(f"{path}: not a readable .npz file ({_short(error)})") from None
    found = arrays.get("schema")
    if found is None or found.shape != () or str(found) != schema:
        got = "no 'schema' key" if found is None else f"schema {_short(found)!r}"
        raise ScenarioFormatError(f"{path}: expected schema {schema!r}, got {got}")
    version = arrays.get("version")
    if version is None or version.shape != () or version.dtype.kind not in "iu":
        raise ScenarioFormatError(f"{path}: missing or malformed 'version' (expected {VERSION})")
    if int(version) != VERSION:
        raise ScenarioFormatError(
            f"{path}: version {int(version)} is not supported (this riskflow_env reads {VERSION})"
        )
    return arrays


def check_arrays(
    path: Path,
    arrays: Mapping[str, np.ndarray | Member],
    spec: dict[str, tuple[tuple, str]],
    optional: dict[str, tuple[tuple, str]] | None = None,
    limits: Mapping[str, tuple[str, int]] | None = None,
) -> None:
    """Every key of ``spec`` (and of ``optional`` when present) has a consistent shape
    (named dims agree across keys; ``N?`` is N or 0; a named dim is at most the value of
    its ``limits`` entry, ``(constant name, value)``) and an allowed dtype kind; any other
    key but ``schema``, ``version`` and the ``EXTRA_PREFIX`` members is refused.
    ``arrays`` may be arrays or :class:`Member` declarations."""
    rules = {**spec, **(optional or {})}
    unexpected = sorted(
        key
        for key in set(arrays) - set(rules) - {"schema", "version"}
        if not key.startswith(EXTRA_PREFIX)
    )
    if unexpected:
        raise ScenarioFormatError(
            f"{path}: unexpected key(s) {_short(unexpected)} (expected {sorted(rules)})"
        )
    missing = sorted(set(spec) - set(arrays))
    if missing:
        raise ScenarioFormatError(f"{path}: missing key(s) {missing}")
    present = {key: rule for key, rule in (optional or {}).items() if key in arrays}
    sizes: dict[str, int] = {}
    for key, (dims, kinds) in {**spec, **present}.items():
        value = arrays[key]
        if value.dtype.kind not in kinds:
            raise ScenarioFormatError(
                f"{path}: {key!r} has dtype {value.dtype}, expected kind {kinds!r}"
            )
        ok = value.ndim == len(dims)
        for dim, size in zip(dims, value.shape, strict=False):
            if isinstance(dim, int):
                ok = ok and size == dim
            elif dim == "N?":
                ok = ok and size in (0, sizes.get("N", size))
            else:
                ok = ok and sizes.setdefault(dim, size) == size
        if ok and "L+1" in sizes and "L" in sizes:
            ok = sizes["L+1"] == sizes["L"] + 1
        if not ok:
            known = ", ".join(f"{k}={v}" for k, v in sizes.items())
            raise ScenarioFormatError(
                f"{path}: {key!r} has shape {value.shape}, expected {dims} ({known})"
            )
        for dim, size in zip(dims, value.shape, strict=False):
            name, limit = (limits or {}).get(
                dim.rstrip("?") if isinstance(dim, str) else "", ("", size)
            )
            if size > limit:
                raise ScenarioFormatError(
                    f"{path}: {key!r} has shape {value.shape}: {dim} = {size} exceeds the limit "
                    f"{name} = {limit}"
                )
