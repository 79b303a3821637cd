"""Low-level ``.npz`` helpers of the scenario format: deterministic writes, schema checks."""

from __future__ import annotations

import os
import secrets
import zipfile
from pathlib import Path

import numpy as np

VERSION = 1
MAX_MEMBER_ELEMENTS = 50_000_000  # [-] largest array in a scenario / map file (= maps.MAX_PIXELS)
MAX_FILE_ARRAY_BYTES = 1024 * 2**20  # [bytes] all arrays of one scenario / map file together


class ScenarioFormatError(ValueError):
    """A scenario or map file that cannot be read: the message names the file and why."""


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez_compressed`` with fixed zip timestamps, written to a temporary name of
    its own (process id and a random token: concurrent writers never share one) and
    renamed over ``path`` (atomic: a reader sees the old file or the whole new one)."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        with zipfile.ZipFile(temporary, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            for key, value in arrays.items():
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                with archive.open(info, "w", force_zip64=True) as handle:
                    np.lib.format.write_array(handle, np.asanyarray(value), allow_pickle=False)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def check_npz_sizes(path: Path) -> None:
    """Refuse ``path`` when an array it declares (read from each ``.npy`` member's header,
    before anything is allocated) exceeds :data:`MAX_MEMBER_ELEMENTS` elements, or when
    all of them together exceed :data:`MAX_FILE_ARRAY_BYTES` (ScenarioFormatError)."""
    total = 0
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
                    elif version == (2, 0):
                        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
                    else:
                        raise ValueError(f"unsupported .npy version {version}")
                count = 1
                for dim in shape:
                    count *= int(dim)
                if count > MAX_MEMBER_ELEMENTS:
                    raise ScenarioFormatError(
                        f"{path}: array {info.filename!r} of shape {shape} exceeds the limit "
                        f"MAX_MEMBER_ELEMENTS = {MAX_MEMBER_ELEMENTS}"
                    )
                total += count * dtype.itemsize
                if total > MAX_FILE_ARRAY_BYTES:
                    raise ScenarioFormatError(
                        f"{path}: arrays totalling over {MAX_FILE_ARRAY_BYTES} bytes exceed the "
                        "limit MAX_FILE_ARRAY_BYTES"
                    )
    except ScenarioFormatError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise ScenarioFormatError(f"{path}: not a readable .npz file ({error})") from None


def read_npz(path: Path, schema: str) -> dict[str, np.ndarray]:
    """All arrays of ``path`` after checking its ``schema`` and ``version``."""
    if not path.is_file():
        raise FileNotFoundError(f"scenario file {path} not found")
    check_npz_sizes(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise ScenarioFormatError(f"{path}: not a readable .npz file ({error})") from None
    found = arrays.get("schema")
    if found is None or found.shape != () or str(found) != schema:
        got = "no 'schema' key" if found is None else f"schema {str(found)!r}"
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
    arrays: dict[str, np.ndarray],
    spec: dict[str, tuple[tuple, str]],
    optional: dict[str, tuple[tuple, str]] | None = None,
) -> None:
    """Every key of ``spec`` (and of ``optional`` when present) has a consistent shape
    (named dims agree across keys; ``N?`` is N or 0) and an allowed dtype kind."""
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
