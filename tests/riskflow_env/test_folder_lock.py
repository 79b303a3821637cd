"""FolderLock: one writer per folder, the holder's pid in the message; output folders made
with an error naming the option."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from riskflow_env.folder_lock import (
    LOCK_NAME,
    FolderLock,
    FolderLocked,
    check_output_folder,
    make_output_file,
    make_output_folder,
    writable_folder,
)

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md


def test_second_lock_is_refused_until_the_first_is_released(tmp_path):
    first, second = FolderLock(tmp_path / "out"), FolderLock(tmp_path / "out")
    with first:
        assert first.held and (tmp_path / "out" / LOCK_NAME).read_text() == f"{os.getpid()}\n"
        with pytest.raises(FolderLocked, match=f"pid {os.getpid()}"):
            second.acquire()
        assert not second.held
        first.acquire()  # holding it already: no-op
    assert not first.held
    with second:
        assert second.held


def test_release_without_acquire_is_a_no_op(tmp_path):
    FolderLock(tmp_path).release()


def test_an_output_folder_the_system_refuses_names_the_option(tmp_path, monkeypatch):
    assert make_output_folder(tmp_path / "a" / "b", "--out").is_dir()
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="--out: .*file exists and is not a folder"):
        make_output_folder(tmp_path / "file" / "x", "--out")

    def refuse(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", refuse)
    refused = r"--folder: cannot make the folder .*\(Permission denied\)"
    with pytest.raises(ValueError, match=refused):
        make_output_folder(tmp_path / "c", "--folder")


def test_a_read_only_folder_is_refused_also_for_root_and_a_writable_file_in_it_is_kept(tmp_path):
    """``chmod a-w``: refused before a run, whoever runs it (os.access lets root write);
    an existing writable file in it may still be written in place (a log appended to)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    log = folder / "events.jsonl"
    log.write_text("")
    folder.chmod(0o555)
    try:
        assert not writable_folder(folder)
        with pytest.raises(ValueError, match="--out: cannot write in the folder .*ro"):
            check_output_folder(folder / "run", "--out")
        with pytest.raises(ValueError, match="path: cannot write in the folder"):
            make_output_file(folder / "scene.npz")
        assert make_output_file(log, in_place=True) == log
    finally:
        folder.chmod(0o755)
