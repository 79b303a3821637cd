"""Files written whole or not at all.

Every result, report, cache and checkpoint the library writes goes to a temporary name of
its own in the target's folder (process id and a random token: concurrent writers never
share one) and is renamed over the target when it is complete (``os.replace``, atomic on
POSIX and Windows). A reader sees the old file or the whole new one, never a torn one,
and a run that dies midway leaves the previous file as it was (the temporary is removed).
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed over ``path`` when the block
    ends without an exception, removed otherwise. ``suffix`` ends the temporary's name (a
    writer that insists on an extension, e.g. ``.npz``)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


@contextmanager
def atomic_file(
    path: str | os.PathLike, mode: str = "wb", encoding: str | None = None
) -> Iterator[IO[Any]]:
    """An open file that replaces ``path`` when the block ends (flushed to disk first), as
    :func:`atomic_path`; ``mode`` ``"wb"`` or ``"w"`` (text, ``encoding``)."""
    if mode not in ("wb", "w"):
        raise ValueError(f"mode must be 'wb' or 'w', got {mode!r}")
    with atomic_path(path) as temporary, open(temporary, mode, encoding=encoding) as file:
        yield file
        file.flush()
        os.fsync(file.fileno())


def write_text(path: str | os.PathLike, text: str) -> None:
    """``text`` (UTF-8) as the whole of ``path``, atomically."""
    with atomic_file(path, "w", encoding="utf-8") as file:
        file.write(text)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """``data`` as the whole of ``path``, atomically."""
    with atomic_file(path) as file:
        file.write(data)


__all__ = ["atomic_file", "atomic_path", "write_bytes", "write_text"]
