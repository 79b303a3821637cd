"""FolderLock: one writer per folder, the holder's pid in the message (issue 19 item 5)."""

from __future__ import annotations

import os

import pytest

from riskflow_env.folder_lock import LOCK_NAME, FolderLock, FolderLocked

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
