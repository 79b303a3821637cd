"""policies.rl.sb3_shards: the scenes of one vector env split over worker processes give the
unsharded env's rollout; the VecEnv API across shards; worker failures raise; bad input.

Tiny configs (3 shipped training scenes, short episodes); no timing assertions.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

from policies.rl.adversary import AdversaryStage, ScenePolicyConfig  # noqa: E402
from policies.rl.envs import EgoEnvConfig  # noqa: E402
from policies.rl.sb3_shards import ShardedEgoVecEnv  # noqa: E402
from policies.rl.sb3_vec_env import SB3EgoVecEnv  # noqa: E402
from policies.rl.vector_env import build_vector_env  # noqa: E402
from riskflow_env.config import EnvConfig  # noqa: E402


def config(kind: str) -> EgoEnvConfig:
    traffic = ScenePolicyConfig(kind=kind, guidance_steps=2, stage=AdversaryStage(k=2))
    return EgoEnvConfig(
        env=EnvConfig(max_agents=8, episode_steps=6),
        traffic=traffic,
        scenes=3,
        base_planner="lane",
        action_repeat=2,
        maneuver_actions=True,
        maneuver_features=True,
    )


def rollout(venv, steps: int = 5) -> list:
    venv.seed(7)
    out = [venv.reset()]
    rng = np.random.default_rng(0)
    for _ in range(steps):  # episodes end at 3 decisions: autoresets included
        out += venv.step(rng.integers(0, 15, venv.num_envs))[:3]
    return out


@pytest.mark.parametrize(("kind", "atol"), [("idm", 1e-9), ("riskflow", 1e-3)])
def test_shards_follow_the_unsharded_env(kind, atol):
    """Scene i of 2 shards is scene i of one vector env: same draws, same seeds; with the
    RiskFlow adversary to the rounding of planning fewer scenes per call."""
    sharded = ShardedEgoVecEnv(config(kind), num_envs=5, shards=2, seed=1)
    try:
        assert (sharded.starts, sharded.stops) == ([0, 3], [3, 5])
        whole = SB3EgoVecEnv(build_vector_env(config(kind), 5, seed=1))
        assert sharded.observation_space == whole.observation_space
        assert sharded.action_space == whole.action_space
        for a, b in zip(rollout(sharded), rollout(whole), strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=atol)
        first = rollout(sharded)
        for a, b in zip(first, rollout(sharded), strict=True):  # same seed: bit for bit
            np.testing.assert_array_equal(a, b)
        assert len(sharded.reset_infos) == 5
    finally:
        sharded.close()


def test_vec_env_api_across_shards():
    sharded = ShardedEgoVecEnv(config("riskflow"), num_envs=3, shards=2)
    try:
        assert sharded.get_attr("action_repeat") == [2, 2, 2]
        assert sharded.get_attr("num_envs", [2, 0]) == [1, 2]  # each scene's shard
        assert sharded.env_method("set_adversary_stage", AdversaryStage(k=1)) == [None] * 3
        assert sharded.env_is_wrapped(object) == [False] * 3
        with pytest.raises(AttributeError, match="no_such_thing"):
            sharded.get_attr("no_such_thing")
        assert sharded.get_attr("action_repeat", 1) == [2]  # the workers live on
        sharded.set_attr("action_repeat", 2)
        with pytest.raises(ValueError, match="set it for all"):
            sharded.set_attr("action_repeat", 2, indices=[0])
        with pytest.raises(ValueError, match="num_envs = 3"):
            sharded.step_async(np.zeros(2, int))
    finally:
        sharded.close()
    with pytest.raises(RuntimeError, match="closed"):
        sharded.reset()


def test_a_failing_worker_raises_with_its_traceback():
    sharded = ShardedEgoVecEnv(config("idm"), num_envs=2, shards=2)
    with pytest.raises(RuntimeError, match="(?s)shard 0 .*RiskFlow adversary"):
        sharded.env_method("set_adversary_stage", AdversaryStage(k=1))  # IDM traffic: no k
    assert sharded.closed and not any(p.is_alive() for p in sharded.processes)

    sharded = ShardedEgoVecEnv(config("idm"), num_envs=2, shards=2)
    sharded.reset()
    sharded.processes[1].kill()
    sharded.processes[1].join()
    with pytest.raises(RuntimeError, match="(?s)shard 1 .*died"):
        sharded.step(np.zeros(2, int))


def test_bad_arguments_name_the_argument():
    with pytest.raises(ValueError, match="shards must be an int >= 1"):
        ShardedEgoVecEnv(config("idm"), num_envs=2, shards=0)
    with pytest.raises(ValueError, match="num_envs must be an int >= 3"):
        ShardedEgoVecEnv(config("idm"), num_envs=2, shards=3)
    with pytest.raises(TypeError, match="EgoEnvConfig"):
        ShardedEgoVecEnv(EnvConfig(), num_envs=2)
