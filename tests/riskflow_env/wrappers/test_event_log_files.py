"""Event logs survive a killed run (issue 19 item 5)."""

from __future__ import annotations

import pytest

from riskflow_env.wrappers import EventLogWrapper, read_event_log
from riskflow_env.wrappers.event_log import EventRecorder
from tests.riskflow_env.hand_made_scenes import make_env

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

VEHICLES = [(0.0, 0.0, 0.0, 0.0), (3.0, 0.0, 0.0, 0.0)]


def _episode(path, **kwargs):
    with EventLogWrapper(make_env(VEHICLES, steps=5), path, **kwargs) as env:
        env.reset(seed=0)
        while env.agents:
            env.step({agent: (0.0, 0.0) for agent in env.agents})


def test_restart_does_not_destroy_an_existing_log(tmp_path):
    path = tmp_path / "events.jsonl"
    _episode(path)
    before = path.read_text()
    assert before
    with pytest.raises(FileExistsError, match="append=True"):
        EventLogWrapper(make_env(VEHICLES), path)
    assert path.read_text() == before
    _episode(path, append=True)
    assert len(read_event_log(path)) == 2 * len(before.splitlines())
    _episode(path, overwrite=True)
    assert path.read_text() == before


def test_empty_existing_file_is_fine(tmp_path):
    path = tmp_path / "events.jsonl"
    path.touch()
    _episode(path)
    assert read_event_log(path)


def test_append_and_overwrite_exclude_each_other(tmp_path):
    with pytest.raises(ValueError, match="exclude"):
        EventRecorder(tmp_path / "x.jsonl", append=True, overwrite=True)


def test_torn_last_line_is_skipped_with_a_warning(tmp_path):
    path = tmp_path / "events.jsonl"
    path.write_text('{"event": "a"}\n{"event": "b"}\n{"event": "summ')
    with pytest.warns(UserWarning, match="torn"):
        assert read_event_log(path) == [{"event": "a"}, {"event": "b"}]


def test_bad_middle_line_raises(tmp_path):
    path = tmp_path / "events.jsonl"
    path.write_text('{"event": "a"}\n{"eve\n{"event": "b"}\n')
    with pytest.raises(ValueError, match="line 2"):
        read_event_log(path)


def test_append_after_a_torn_line_drops_it(tmp_path):
    path = tmp_path / "events.jsonl"
    path.write_text('{"event": "a"}\n{"event": "summ')
    with pytest.warns(UserWarning, match="torn"):
        _episode(path, append=True)
    events = read_event_log(path)
    assert events[0] == {"event": "a"} and len(events) > 1


def test_append_refuses_a_file_that_is_not_an_event_log(tmp_path):
    """Appending first drops a torn tail: another file would be truncated, so it is refused."""
    path = tmp_path / "notes.txt"
    path.write_text("my notes\nsecond line without newline")
    with pytest.raises(ValueError, match="is not an event log .* refusing to append"):
        EventLogWrapper(make_env(VEHICLES), path, append=True)
    assert path.read_text() == "my notes\nsecond line without newline"


def test_a_binary_file_read_as_a_log_is_named(tmp_path):
    path = tmp_path / "scene.npz"
    path.write_bytes(b"PK\x03\x04\xff\xfe\x00binary")
    with pytest.raises(ValueError, match="scene.npz is not an event log"):
        read_event_log(path)
    with pytest.raises(ValueError, match="path must be a file path"):
        read_event_log(3)  # not a file descriptor


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"path": 123}, ValueError, "path must be a file path"),
        ({"append": "yes"}, ValueError, "append must be True or False"),
        ({"overwrite": 1}, ValueError, "overwrite must be True or False"),
    ],
)
def test_bad_arguments(tmp_path, kwargs, error, message):
    kwargs = {"path": tmp_path / "e.jsonl", **kwargs}
    with pytest.raises(error, match=message):
        EventLogWrapper(make_env(VEHICLES), **kwargs)


def test_output_paths_that_cannot_be_logs(tmp_path):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match="afile exists and is not a folder"):
        EventLogWrapper(make_env(VEHICLES), tmp_path / "afile" / "e.jsonl")
    with pytest.raises(ValueError, match="is a folder, not a file"):
        EventLogWrapper(make_env(VEHICLES), tmp_path)
    with pytest.raises(TypeError, match="EventLogWrapper: env must be a riskflow_v0 env"):
        EventLogWrapper({"not": "an env"}, tmp_path / "e.jsonl")


def test_append_after_a_torn_first_row_starts_the_log_again(tmp_path):
    """A run killed while writing its first row leaves a torn line: an event log still."""
    path = tmp_path / "events.jsonl"
    path.write_text('\n{"event": "collision_start", "epi')
    with pytest.warns(UserWarning, match="dropping a torn last line"):
        _episode(path, append=True)
    events = read_event_log(path)
    assert events[0]["episode"] == 0 and events[-1]["event"] == "episode_summary"
