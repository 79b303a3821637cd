"""Gymnasium's ``RecordVideo`` over the ego view writes a video (the ``video`` extra:
RecordVideo writes its files with moviepy)."""

from __future__ import annotations

import gymnasium
import pytest

from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig
from riskflow_env.wrappers import EgoEnv

pytestmark = pytest.mark.extras
pytest.importorskip(
    "moviepy", reason="moviepy is not installed (pip install -e '.[video]'; .ci/run installs it)"
)


def test_record_video_writes_an_episode(tmp_path):
    scenes = HighwayTrafficSource(TrafficConfig(families=("highway",), num_vehicles=(3, 4)))
    env = EgoEnv(config=EnvConfig(max_agents=4, episode_steps=8), scenarios=scenes,
                 render_mode="rgb_array")  # fmt: skip
    env = gymnasium.wrappers.RecordVideo(env, str(tmp_path), episode_trigger=lambda e: True)
    env.reset(seed=0)
    done = False
    while not done:
        *_, terminated, truncated, _ = env.step(env.action_space.sample())
        done = terminated or truncated
    env.close()
    videos = list(tmp_path.glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0
