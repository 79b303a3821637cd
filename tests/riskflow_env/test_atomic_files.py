"""Files written whole or not at all (riskflow_env.atomic_files)."""

from __future__ import annotations

import pytest

from riskflow_env.atomic_files import atomic_file, atomic_path, write_bytes, write_text


def test_a_write_replaces_the_file_whole_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "result.json"
    write_text(path, "old\n")
    write_text(path, "new\n")
    assert path.read_text() == "new\n" and [p.name for p in tmp_path.iterdir()] == [path.name]
    write_bytes(path, b"\x00\x01")
    assert path.read_bytes() == b"\x00\x01"


def test_a_write_that_fails_midway_keeps_the_old_file(tmp_path):
    path = tmp_path / "report.md"
    write_text(path, "complete\n")
    with pytest.raises(RuntimeError), atomic_file(path, "w", encoding="utf-8") as file:
        file.write("half of a ")
        raise RuntimeError("the run dies here")
    assert path.read_text() == "complete\n" and [p.name for p in tmp_path.iterdir()] == [path.name]


def test_a_writer_that_insists_on_an_extension_gets_its_suffix(tmp_path):
    with atomic_path(tmp_path / "scene.npz", suffix=".tmp.npz") as temporary:
        assert temporary.name.startswith(".scene.npz.") and temporary.name.endswith(".tmp.npz")
        temporary.write_bytes(b"x")
    assert (tmp_path / "scene.npz").read_bytes() == b"x"
    with (
        pytest.raises(ValueError, match="mode must be 'wb' or 'w'"),
        atomic_file(path := tmp_path / "a", "a"),
    ):
        pass
    assert not path.exists()
