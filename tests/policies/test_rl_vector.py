"""policies.rl.vector_env: N scenes stepped as one batch give the single ego env's episodes;
autoreset, seeding, spaces, SB3's VecEnv and PPO, argument errors.

Tiny configs (3 roads of their own, 4-7 vehicles, short episodes, a randomly initialised
generator with 4 guidance steps); no timing assertions.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

from gymnasium.vector import AutoresetMode  # noqa: E402

from policies.riskflow.policy import RiskFlowAdversary  # noqa: E402
from policies.rl.envs import EgoTrainingEnv  # noqa: E402
from policies.rl.vector_env import EgoVectorEnv  # noqa: E402
from riskflow_env.config import EnvConfig  # noqa: E402
from riskflow_env.wrappers import EgoEnv  # noqa: E402
from tests.policies.straight_scenes import make_scenario  # noqa: E402

CONFIG = EnvConfig(
    max_agents=8, episode_steps=30, terminate_on_collision="none", terminate_on_offroad="none"
)


SCENES = [make_scenario(index) for index in range(3)]


def riskflow(model, normalizer) -> RiskFlowAdversary:
    options = {"k": 2, "guidance_steps": 4, "planning_interval": 0.3, "seed": 4}
    return RiskFlowAdversary(generator=model, normalizer=normalizer, **options)


def single_env(config: EnvConfig, policy=None, **interface) -> EgoTrainingEnv:
    return EgoTrainingEnv(EgoEnv(config=config, scenarios=SCENES, policy=policy), **interface)


def close(a, b, atol: float) -> None:
    np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=0, atol=atol)


def random_actions(rng: np.random.Generator, count: int) -> np.ndarray:
    return rng.uniform(-1.0, 1.0, (count, 2))


@pytest.mark.parametrize(
    ("traffic", "interface", "atol"),
    [
        ("idm", {}, 1e-9),
        ("riskflow", {}, 2e-4),
        ("idm", {"base_planner": "idm", "action_repeat": 2, "maneuver_features": True}, 1e-9),
    ],
)
def test_scenes_follow_the_single_env(traffic, interface, atol, tiny_meanflow, tiny_normalizer):
    """While no scene resets, scene b of a vector env reset with seed s is a single
    EgoTrainingEnv reset with seed s + b, given the same actions (the scenes are drawn
    from three roads: own maps, 4-7 vehicles, padded to 8 slots)."""
    count, seed, steps = 3, 5, 12
    make = (lambda: riskflow(tiny_meanflow, tiny_normalizer)) if traffic == "riskflow" else None
    policy = make() if make else None
    vector = EgoVectorEnv(count, config=CONFIG, scenarios=SCENES, policy=policy, **interface)
    singles = [single_env(CONFIG, make() if make else None, **interface) for _ in range(count)]
    observations, _ = vector.reset(seed=seed)
    for index, env in enumerate(singles):
        observation, _ = env.reset(seed=seed + index)
        close(observations[index], observation, atol)
    rng = np.random.default_rng(0)
    for _ in range(steps):
        actions = random_actions(rng, count)
        observations, rewards, terminated, truncated, infos = vector.step(actions)
        assert not (terminated | truncated).any()
        for index, env in enumerate(singles):
            observation, reward, done, cut, info = env.step(actions[index])
            close(observations[index], observation, atol)
            close(rewards[index], reward, atol)
            assert (terminated[index], truncated[index]) == (done, cut)
            for name, value in info["reward_terms"].items():
                close(infos["reward_terms"][name][index], value, atol)
            assert infos["collided"][index] == info["collided"]
            assert infos["collided_with"][index] == info["collided_with"]


@pytest.mark.parametrize(("traffic", "atol"), [("idm", 1e-9), ("riskflow", 2e-4)])
def test_autoreset_draws_the_next_scene_and_reports_the_final_one(
    traffic, atol, tiny_meanflow, tiny_normalizer
):
    """Short episodes: a finished scene is reset in the same step (SAME_STEP), as a single
    env reset without a seed (its generator and its adversary's episode count go on);
    final_obs / final_info hold the last step, the episode outcome included."""
    config = EnvConfig(max_agents=8, episode_steps=4, terminate_on_offroad="none")
    count, seed = 2, 3
    make = (lambda: riskflow(tiny_meanflow, tiny_normalizer)) if traffic == "riskflow" else None
    vector = EgoVectorEnv(count, config=config, scenarios=SCENES, policy=make() if make else None)
    assert vector.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    singles = [single_env(config, make() if make else None) for _ in range(count)]
    vector.reset(seed=seed)
    for index, env in enumerate(singles):
        env.reset(seed=seed + index)
    rng = np.random.default_rng(1)
    resets = 0
    for _ in range(11):
        actions = random_actions(rng, count)
        observations, rewards, terminated, truncated, infos = vector.step(actions)
        done = terminated | truncated
        for index, env in enumerate(singles):
            observation, reward, ended, cut, info = env.step(actions[index])
            close(rewards[index], reward, atol)
            assert done[index] == (ended or cut)
            if ended or cut:
                resets += 1
                assert infos["_final_obs"][index] and infos["_final_info"][index]
                close(infos["final_obs"][index], observation, atol)
                final = infos["final_info"]
                assert final["_ego_collision"][index]
                assert final["ego_collision"][index] == info["ego_collision"]
                assert final["ego_offroad"][index] == info["ego_offroad"]
                observation, _ = env.reset()
            close(observations[index], observation, atol)
        if not done.any():
            assert "final_obs" not in infos
    assert resets >= 4  # every scene went through at least two episodes


def test_next_step_autoreset_resets_at_the_following_call():
    """NEXT_STEP (Gymnasium's default): the step that ends the episodes returns their last
    observations; the next call resets them (reward 0, action ignored), to what SAME_STEP
    returned at once; then both go on alike."""
    config = EnvConfig(max_agents=8, episode_steps=4, terminate_on_collision="none",
                       terminate_on_offroad="none")  # fmt: skip
    same = EgoVectorEnv(2, config=config, scenarios=SCENES)
    lagged = EgoVectorEnv(2, config=config, scenarios=SCENES, autoreset_mode="NextStep")
    assert lagged.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    same.reset(seed=7)
    lagged.reset(seed=7)
    rng = np.random.default_rng(3)
    for _ in range(4):
        actions = random_actions(rng, 2)
        expected = same.step(actions)
        got = lagged.step(actions)
    assert (expected[3] & got[3]).all()  # both truncated at step 4
    close(got[0], np.stack(expected[4]["final_obs"]), 0.0)
    assert got[4]["_ego_collision"].all() and "final_obs" not in got[4]
    reset = lagged.step(random_actions(rng, 2))
    close(reset[0], expected[0], 0.0)
    assert not (reset[1].any() or reset[2].any() or reset[3].any())
    actions = random_actions(rng, 2)
    close(lagged.step(actions)[0], same.step(actions)[0], 0.0)
    with pytest.raises(ValueError, match="autoreset_mode"):
        EgoVectorEnv(2, config=config, scenarios=SCENES, autoreset_mode="Disabled")
    from policies.rl.sb3_vec_env import SB3EgoVecEnv

    with pytest.raises(ValueError, match="autoreset_mode"):
        SB3EgoVecEnv(lagged)


@pytest.mark.parametrize("mode", ["SameStep", "NextStep"])
def test_gymnasium_vector_wrappers(mode):
    """Gymnasium's RecordEpisodeStatistics reads the autoreset mode from the metadata and
    counts 5-step episodes in both modes; its observation wrappers take NextStep."""
    from gymnasium.wrappers.vector import NormalizeObservation, RecordEpisodeStatistics

    config = EnvConfig(max_agents=8, episode_steps=5, terminate_on_offroad="none")
    env = EgoVectorEnv(2, config=config, scenarios=SCENES, autoreset_mode=mode)
    if mode == "NextStep":
        env = NormalizeObservation(env)
    env = RecordEpisodeStatistics(env)
    env.reset(seed=0)
    lengths = []
    for _ in range(12):
        *_, infos = env.step(np.zeros((2, 2)))
        if "episode" in infos:
            lengths += infos["episode"]["l"][infos["_episode"]].tolist()
    assert lengths == [5, 5, 5, 5]


def test_same_seed_same_rollout_bit_for_bit(tiny_meanflow, tiny_normalizer):
    """Two vector envs with the RiskFlow adversary, the same seed and actions, through
    autoresets: identical observations, rewards and flags."""
    config = EnvConfig(max_agents=8, episode_steps=6)

    def rollout() -> list[np.ndarray]:
        env = EgoVectorEnv(
            3, config=config, scenarios=SCENES, policy=riskflow(tiny_meanflow, tiny_normalizer)
        )
        observations, _ = env.reset(seed=11)
        rng, out = np.random.default_rng(2), [observations]
        for _ in range(14):
            observations, rewards, terminated, truncated, _ = env.step(random_actions(rng, 3))
            out += [observations, rewards, terminated, truncated]
        return out

    first, second = rollout(), rollout()
    assert all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))


def test_spaces_seeding_and_step_types():
    """gymnasium env_checker-style checks on the vector API: batched spaces contain what
    reset and step return; dtypes and shapes; reset(seed) repeats; a list of seeds."""
    count = 3
    env = EgoVectorEnv(count, config=CONFIG, scenarios=SCENES)
    assert env.observation_space.shape == (count, *env.single_observation_space.shape)
    assert env.action_space.shape == (count, 2)
    observations, infos = env.reset(seed=0)
    assert observations in env.observation_space and observations.dtype == np.float32
    assert infos["_collided"].all() and infos["reward_terms"]["_speed"].all()
    again, _ = env.reset(seed=0)
    np.testing.assert_array_equal(observations, again)
    listed, _ = env.reset(seed=[0, 1, 2])
    np.testing.assert_array_equal(observations, listed)
    env.action_space.seed(0)
    observations, rewards, terminated, truncated, infos = env.step(env.action_space.sample())
    assert observations in env.observation_space
    assert rewards.shape == (count,) and rewards.dtype == np.float64
    assert terminated.dtype == bool and truncated.dtype == bool and terminated.shape == (count,)
    maneuvers = EgoVectorEnv(2, config=CONFIG, scenarios=SCENES, maneuver_actions=True)
    maneuvers.reset(seed=0)
    assert maneuvers.action_space.shape == (2,)
    observations, *_ = maneuvers.step(maneuvers.action_space.sample())
    assert observations in maneuvers.observation_space
    env.close()


def test_sb3_vec_env_runs_ppo():
    """SB3's VecEnv API (seed, reset, step with terminal observations) and a few PPO
    updates on the vector env."""
    from stable_baselines3 import PPO

    from policies.rl.sb3_vec_env import sb3_ego_vec_env

    config = EnvConfig(max_agents=8, episode_steps=5)
    venv = sb3_ego_vec_env(EgoVectorEnv(2, config=config, scenarios=SCENES))
    venv.seed(3)
    first = venv.reset()
    venv.seed(3)
    np.testing.assert_array_equal(first, venv.reset())
    for _ in range(5):
        observations, rewards, dones, infos = venv.step(np.zeros((2, 2), np.float32))
    assert dones.all() and all("terminal_observation" in info for info in infos)
    assert all(info["TimeLimit.truncated"] and "episode" in info for info in infos)
    model = PPO("MlpPolicy", venv, n_steps=8, batch_size=8, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=16)
    assert model.num_timesteps >= 16


def test_bad_arguments_name_the_argument():
    with pytest.raises(ValueError, match="num_scenes"):
        EgoVectorEnv(0, config=CONFIG, scenarios=SCENES)
    with pytest.raises(TypeError, match="num_scenes"):
        EgoVectorEnv("2", config=CONFIG, scenarios=SCENES)
    with pytest.raises(ValueError, match="action_repeat"):
        EgoVectorEnv(2, config=CONFIG, scenarios=SCENES, action_repeat=0)
    with pytest.raises(ValueError, match="base_planner"):
        EgoVectorEnv(2, config=CONFIG, scenarios=SCENES, base_planner="mpc")
    env = EgoVectorEnv(2, config=CONFIG, scenarios=SCENES)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=-1)
    with pytest.raises(TypeError, match="seed"):
        env.reset(seed=[1, 2, 3])
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must be .*shape \(num_envs, 2\)"):
        env.step(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="actions must be finite"):
        env.step(np.array([[0.0, np.nan], [0.0, 0.0]]))
    discrete = EgoVectorEnv(2, config=CONFIG, scenarios=SCENES, maneuver_actions=True)
    discrete.reset(seed=0)
    with pytest.raises(ValueError, match="maneuver indices"):
        discrete.step(np.array([0, 99]))


def test_build_vector_env_follows_the_training_config():
    """The vector counterpart of build_env: the config's scenes, interface and traffic."""
    from policies.rl.adversary import ScenePolicyConfig
    from policies.rl.envs import EgoEnvConfig
    from policies.rl.vector_env import build_vector_env

    config = EgoEnvConfig(
        env=EnvConfig(max_agents=8, episode_steps=5),
        traffic=ScenePolicyConfig(kind="idm"),
        scenes=2,
        action_repeat=2,
        maneuver_actions=True,
    )
    env = build_vector_env(config, num_envs=2, seed=0)
    assert env.action_repeat == 2 and env.action_space.shape == (2,)
    env.reset(seed=0)
    observations, rewards, *_ = env.step(np.array([1, 4]))
    assert observations.shape == (2, env.single_observation_space.shape[0])
