"""VideoRecorder: GIF and MP4 files per episode or per run, read back."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest
import shapely

import riskflow_env
from riskflow_env.config import EnvConfig
from riskflow_env.maps import from_polygons
from riskflow_env.render import RenderConfig
from riskflow_env.scenarios import Scenario
from riskflow_env.wrappers import VideoRecorder

SMALL = RenderConfig(width_px=96, height_px=64, view_width=40.0)


def make_env(steps: int = 5):
    """Two vehicles on a straight road (10 and 5 m/s), ``steps`` steps per episode."""
    t = np.arange(-30, 11) * 0.1
    speed = np.array([[10.0], [5.0]])
    x, y = np.array([[0.0], [15.0]]) + speed * t, np.array([[0.0], [4.0]]) + 0.0 * t
    scenario = Scenario(
        map=from_polygons(shapely.box(-40.0, -8.0, 80.0, 8.0), resolution=0.5),
        states=np.stack([x, y, speed + 0.0 * t, 0.0 * x], axis=-1),
        valid=np.ones(x.shape, dtype=bool),
        length=np.full(2, 4.5),
        width=np.full(2, 2.0),
    )
    return riskflow_env.parallel_env(
        config=EnvConfig(max_agents=2, episode_steps=steps), scenarios=scenario
    )


def play(env, episodes: int = 1) -> None:
    for episode in range(episodes):
        env.reset(seed=episode)
        while env.agents:
            env.step({agent: np.zeros(2) for agent in env.agents})


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_one_file_per_episode(tmp_path, suffix):
    env = VideoRecorder(make_env(), tmp_path / f"episode_{{episode}}{suffix}", config=SMALL)
    play(env, episodes=2)
    env.close()
    assert env.paths == [tmp_path / f"episode_0{suffix}", tmp_path / f"episode_1{suffix}"]
    for path in env.paths:
        frames = (
            iio.imread(path, index=None) if suffix == ".gif" else iio.imread(path, plugin="FFMPEG")
        )
        assert frames.shape[0] == 6  # after reset and after each of 5 steps
        assert frames.shape[1:3] == (64, 96)


def test_one_file_for_the_run_and_trigger(tmp_path):
    path = tmp_path / "run.gif"
    with VideoRecorder(make_env(), path, config=SMALL, episode_trigger=lambda e: e != 1) as env:
        play(env, episodes=3)
    assert env.paths == [path]
    assert iio.imread(path, index=None).shape == (12, 64, 96, 3)  # episodes 0 and 2


def test_frames_match_the_renderer(tmp_path):
    env = VideoRecorder(make_env(steps=1), tmp_path / "one.gif", config=SMALL)
    env.reset(seed=0)
    expected = env.renderer.render(env.unwrapped)
    env.close()
    np.testing.assert_array_equal(iio.imread(tmp_path / "one.gif", index=0), expected)


def test_bad_suffix():
    with pytest.raises(ValueError, match="path must end in one of"):
        VideoRecorder(make_env(), "video.txt")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"path": "v_{ep}.mp4"}, r"path may hold one field, \{episode\}"),
        ({"path": "v_{}.mp4"}, r"path may hold one field"),
        ({"path": "v_{episode[0]}.gif"}, r"path may hold one field"),
        ({"path": None}, "path must be a file path"),
        ({"fps": "10"}, "fps must be a finite number > 0"),
        ({"fps": 0}, "fps must be a finite number > 0"),
        ({"fps": float("nan")}, "fps must be a finite number > 0"),
        ({"fps": True}, "fps must be a finite number > 0"),
        ({"episode_trigger": 5}, "episode_trigger must be a function"),
    ],
)
def test_bad_arguments_are_refused_when_built(tmp_path, kwargs, message):
    """Each mistake is named when the recorder is made, not at the first reset."""
    kwargs = {"path": tmp_path / "v.gif", **kwargs}
    with pytest.raises(ValueError, match=message):
        VideoRecorder(make_env(), **kwargs)


def test_not_an_env_and_an_unwritable_folder(tmp_path, monkeypatch):
    with pytest.raises(TypeError, match="VideoRecorder: env must be a riskflow_v0 env"):
        VideoRecorder("env", tmp_path / "v.gif")
    monkeypatch.setattr("os.access", lambda path, mode: False)  # as for a read-only folder
    with pytest.raises(ValueError, match="path: cannot write in the folder"):
        VideoRecorder(make_env(), tmp_path / "videos" / "v_{episode}.gif")


def test_numpy_fps_and_a_path_object(tmp_path):
    recorder = VideoRecorder(make_env(), tmp_path / "run.gif", fps=np.float64(5))
    assert recorder.fps == 5.0 and type(recorder.fps) is float and not recorder.per_episode
    recorder.close()
    braces = VideoRecorder(make_env(), tmp_path / "v_{{x}}.gif")  # literal braces: one file
    assert not braces.per_episode
    braces.close()
