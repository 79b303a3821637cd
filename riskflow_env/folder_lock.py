"""One writer per output folder: an exclusive lock file holding the writer's pid.

:class:`FolderLock` takes a non-blocking exclusive lock on ``<folder>/writer.lock``
(``fcntl.flock`` on POSIX, ``msvcrt.locking`` on Windows) and writes this process's
pid into it. A second process gets :class:`FolderLocked` naming the holder's pid. The
operating system drops the lock when the holder ends, ``kill -9`` included, so a killed
run never blocks its own resume; the file itself stays (deleting it could race).
Used by ``riskflow-eval`` (results folders) and ``riskflow-data generate`` (banks).
:func:`check_output_folder` checks such a folder before anything is written (not a file,
and one this process may write in: :func:`writable_folder`), :func:`make_output_folder`
creates it and :func:`make_output_file` prepares one output file, each with an error
naming the option.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO, Any

LOCK_NAME = "writer.lock"


class FolderLocked(ValueError):
    """Another process is writing into the folder."""


def check_output_folder(folder: str | os.PathLike, option: str = "--out") -> None:
    """ValueError naming ``option`` when ``folder``, or its nearest existing parent, is
    not a folder (an existing file would make the writer's ``mkdir`` fail) or is one this
    process may not write in (checked before a run, not after it)."""
    path = Path(folder)
    for existing in (path, *path.parents):
        if existing.exists():
            if not existing.is_dir():
                raise ValueError(f"{option}: {existing} exists and is not a folder")
            if not writable_folder(existing):
                raise ValueError(f"{option}: cannot write in the folder {existing}")
            return


def writable_folder(folder: str | os.PathLike) -> bool:
    """This process may create files in ``folder``, and its mode grants writing to someone:
    a folder made read-only (``chmod a-w``) counts as read-only also for root, whom
    ``os.access`` lets write anywhere."""
    return os.access(folder, os.W_OK | os.X_OK) and bool(os.stat(folder).st_mode & 0o222)


def make_output_folder(folder: str | os.PathLike, option: str = "--out") -> Path:
    """Create ``folder`` and its parents (:func:`check_output_folder` first); ValueError
    naming ``option`` when the system refuses (a read-only or virtual file system, no
    permission)."""
    check_output_folder(folder, option)
    path = Path(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(
            f"{option}: cannot make the folder {path} ({err.strerror or err})"
        ) from None
    return path


def file_path(path: object, option: str = "path") -> Path:
    """``path`` as a ``Path``; a ValueError naming ``option`` unless it is a ``str`` or an
    ``os.PathLike`` (an int would open a file descriptor, None the wrong file)."""
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{option} must be a file path (str or os.PathLike), got {path!r}")
    return Path(path)


def make_output_file(path: str | os.PathLike, option: str = "path", in_place: bool = False) -> Path:
    """``path`` as a ``Path`` to write, its folder made (:func:`make_output_folder`); a
    ValueError naming ``option`` when it is a folder or its folder cannot be made or
    written in. ``in_place``: the writer opens ``path`` itself (no temporary file beside
    it), so an existing file this process may write is enough, whatever its folder."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{option}: {path} is a folder, not a file")
    if not (in_place and path.is_file() and os.access(path, os.W_OK)):
        make_output_folder(path.parent, option)
    return path


def _try_lock(file: IO[Any]) -> bool:
    """Take an exclusive, non-blocking lock on ``file``; False if another process has it."""
    try:
        if os.name == "nt":
            import msvcrt

            file.seek(0)
            msvcrt.locking(file.fileno(), msvcrt.LK_NBLCK, 1)
        else:
            import fcntl

            fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True


class FolderLock:
    """The writer lock of ``folder`` (module docstring).

    Args:
        folder: the output folder (created when the lock is taken).
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self._file: IO[Any] | None = None

    @property
    def held(self) -> bool:
        """This object holds the lock."""
        return self._file is not None

    def acquire(self) -> None:
        """Take the lock (no-op if held); FolderLocked naming the holder's pid otherwise."""
        if self._file is not None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        file = open(self.path, "a+", encoding="utf-8")  # noqa: SIM115 (held open)
        if not _try_lock(file):
            file.seek(0)
            try:
                holder = file.read(200).strip() or "unknown"
            except OSError:  # Windows: the locked byte cannot be read
                holder = "unknown"
            file.close()
            raise FolderLocked(
                f"{self.folder} is being written by another run (pid {holder}, lock file "
                f"{self.path}); wait for it to finish or use another folder"
            )
        file.seek(0)
        file.truncate()
        file.write(f"{os.getpid()}\n")
        file.flush()
        self._file = file

    def release(self) -> None:
        """Give the lock back (if held); closing the file releases it."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> FolderLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
