"""policies.rl: action scaling, curriculum, adversary stages, the ego training env, the
training and evaluation examples with a tiny budget, and the multi-agent (SuperSuit) path.

Needs the ``rl`` extra (stable-baselines3, supersuit); skipped without it. No timing
assertions: the examples run a few hundred steps with a cheap adversary (2 guidance steps,
re-plan every 1 s) and short episodes.
"""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

from policies.rl.adversary import (  # noqa: E402
    AdversaryStage,
    ScenePolicyConfig,
    apply_stage,
    make_traffic,
)
from policies.rl.curriculum import LinearCurriculum  # noqa: E402
from policies.rl.envs import EgoEnvConfig, build_env, compose_action, scale_action  # noqa: E402
from policies.rl.marl import AdversaryRewardConfig, adversary_reward  # noqa: E402
from policies.rl.paired import PAIRED_OUTCOMES, paired_counts  # noqa: E402
from policies.statistics import paired_difference  # noqa: E402
from riskflow_env.config import DynamicsConfig, EnvConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TINY_TRAFFIC = ScenePolicyConfig(stage=AdversaryStage(k=2), guidance_steps=2, planning_interval=1.0)


def run(script: str, *args: str | Path) -> str:
    """Run an example in a subprocess; its stdout (fails with stderr on a non-zero exit)."""
    command = [sys.executable, str(ROOT / "examples" / script), *map(str, args)]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_scale_action_keeps_zero_and_reaches_the_bounds():
    dynamics = DynamicsConfig()
    np.testing.assert_allclose(scale_action(np.zeros(2), dynamics), [0.0, 0.0])
    np.testing.assert_allclose(scale_action(np.array([-1.0, -1.0]), dynamics), [-8.0, -1.0])
    np.testing.assert_allclose(scale_action(np.array([1.0, 0.5]), dynamics), [5.0, 0.5])
    np.testing.assert_allclose(scale_action(np.array([3.0, -7.0]), dynamics), [5.0, -1.0])


def test_compose_action_adds_the_base_planner_and_clips():
    dynamics = DynamicsConfig()
    base = np.array([1.0, -0.2])
    np.testing.assert_allclose(compose_action(np.zeros(2), base, dynamics), base)
    np.testing.assert_allclose(compose_action(np.array([0.2, 0.1]), base, dynamics), [2.0, -0.1])
    np.testing.assert_allclose(compose_action(np.ones(2), base, dynamics), [5.0, 0.8])
    np.testing.assert_allclose(compose_action(np.ones(2), None, dynamics), [5.0, 1.0])


@pytest.mark.parametrize("base", ["idm", "lane"])
def test_residual_env_drives_as_its_base_with_zero_actions(base):
    from policies.planners import IDMPlanner

    config = EgoEnvConfig(
        env=EnvConfig(episode_steps=3), traffic=TINY_TRAFFIC, scenes=1, base_planner=base
    )
    env, idm = build_env(config, seed=0), IDMPlanner()
    observation, _ = env.reset(seed=0)
    view = env.unwrapped.parallel_env.view()
    idm.reset(view)
    expected = idm(observation, view)
    if base == "lane":  # IDM's steering, no acceleration: the policy owns it
        expected = np.array([0.0, expected[1]])
    env.step(np.zeros(2, np.float32))
    np.testing.assert_allclose(env.unwrapped.parallel_env.scene.last_action[0], expected)
    with pytest.raises(ValueError, match="base_planner"):
        build_env(EgoEnvConfig(base_planner="mpc"))


def test_action_repeat_holds_the_policy_action():
    from policies.rl.evaluation import PPOPlanner

    config = EgoEnvConfig(
        env=EnvConfig(episode_steps=7), traffic=TINY_TRAFFIC, scenes=1, action_repeat=3
    )
    env = build_env(config, seed=0)
    env.reset(seed=0)
    base = env.unwrapped.parallel_env
    env.step(np.array([0.5, 0.0], np.float32))
    assert base.view().step == 3  # one decision, three env steps
    np.testing.assert_allclose(base.scene.last_action[0], [2.5, 0.0])
    *_, terminated, truncated, _ = env.step(np.zeros(2, np.float32))
    *_, terminated, truncated, _ = env.step(np.zeros(2, np.float32))  # truncated at step 7
    assert truncated and base.view().step == 7
    with pytest.raises(ValueError, match="action_repeat"):
        build_env(EgoEnvConfig(traffic=TINY_TRAFFIC, scenes=1, action_repeat=0))

    class Counting:  # a model whose n-th decision is (n / 10, 0)
        calls = 0

        def predict(self, observation, deterministic=True):
            self.calls += 1
            return np.array([self.calls / 10, 0.0]), None

    planner = PPOPlanner(Counting(), action_repeat=3)
    planner.reset(None)
    accels = [planner(np.zeros(3))[0] for _ in range(7)]
    np.testing.assert_allclose(accels, [0.5, 0.5, 0.5, 1.0, 1.0, 1.0, 1.5])


@pytest.mark.parametrize(
    ("changes", "error", "message"),
    [
        ({"action_repeat": 0}, ValueError, "EgoEnvConfig.action_repeat must be an int >= 1, got 0"),
        ({"split": "x"}, ValueError, "EgoEnvConfig.split must be one of ('eval', 'train')"),
        ({"base_planner": "x"}, ValueError, "EgoEnvConfig.base_planner must be one of ('none',"),
        ({"maneuver_set": "x"}, ValueError, "EgoEnvConfig.maneuver_set must be one of"),
        ({"scenes": 0}, ValueError, "EgoEnvConfig.scenes must be an int >= 1, got 0"),
        ({"maneuver_actions": 1}, TypeError, "EgoEnvConfig.maneuver_actions must be a bool"),
        ({"env": None}, TypeError, "EgoEnvConfig.env must be of type EnvConfig, got NoneType"),
        ({"traffic": "idm"}, TypeError, "EgoEnvConfig.traffic must be of type ScenePolicyConfig"),
        ({"ego_collision": np.nan}, ValueError, "AdversaryRewardConfig.ego_collision must be a"),
        ({"offroad": -np.inf}, ValueError, "AdversaryRewardConfig.offroad must be a finite number"),
        ({"closeness": "0.1"}, ValueError, "AdversaryRewardConfig.closeness must be a finite"),
        ({"closeness_radius": 0.0}, ValueError, "AdversaryRewardConfig.closeness_radius must be >"),
    ],
)  # fmt: skip
def test_configs_refuse_bad_values_when_built(changes, error, message):
    config = {"EgoEnvConfig": EgoEnvConfig, "AdversaryRewardConfig": AdversaryRewardConfig}
    with pytest.raises(error, match="^" + re.escape(message)):
        config[message.split(".")[0]](**changes)  # the class the message names


def test_maneuver_features_in_training_and_evaluation_agree():
    from policies.rl.evaluation import PPOPlanner
    from policies.rl.features import ManeuverFeatures

    plain = build_env(EgoEnvConfig(traffic=TINY_TRAFFIC, scenes=1))
    config = EgoEnvConfig(traffic=TINY_TRAFFIC, scenes=1, maneuver_features=True)
    env = build_env(config)
    features = ManeuverFeatures()
    assert env.observation_space.shape[0] == plain.observation_space.shape[0] + features.size
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    view = env.unwrapped.parallel_env.view()
    raw = observation[: -features.size]

    class Recording:  # records what the policy network is given
        def predict(self, observation, deterministic=True):
            self.seen = observation
            return np.zeros(2), None

    model = Recording()
    planner = PPOPlanner(model, maneuver_features=True)
    planner.reset(view)
    planner(raw, view)
    np.testing.assert_array_equal(model.seen, observation)


def test_the_mpc_maneuver_set_for_features_and_actions():
    from policies.planners.sampling_mpc import candidate_actions
    from policies.rl.envs import EgoInterface
    from policies.rl.features import ManeuverFeatures, maneuvers

    np.testing.assert_array_equal(maneuvers(maneuver_set="mpc"), candidate_actions(30))
    compact = build_env(EgoEnvConfig(traffic=TINY_TRAFFIC, scenes=1, maneuver_features=True))
    config = EgoEnvConfig(
        traffic=TINY_TRAFFIC, scenes=1, maneuver_features=True, maneuver_actions=True,
        maneuver_set="mpc",
    )  # fmt: skip
    env = build_env(config, seed=0)
    extra = ManeuverFeatures(maneuver_set="mpc").size - ManeuverFeatures().size
    assert extra == 2 * (200 - 15)
    assert env.observation_space.shape[0] == compact.observation_space.shape[0] + extra
    assert env.action_space.n == 200
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    env.step(199)
    with pytest.raises(ValueError, match="maneuver_set must be one of"):
        EgoInterface(DynamicsConfig(), maneuver_actions=True, maneuver_set="fine")


def test_maneuver_actions_follow_the_chosen_maneuver():
    from policies.rl.evaluation import PPOPlanner
    from policies.rl.features import maneuvers

    table = maneuvers()
    dynamics = DynamicsConfig()
    np.testing.assert_allclose(compose_action(4, None, dynamics, table, 3), table[4, 3])
    np.testing.assert_allclose(  # the base is added and the sum clipped to the bounds
        compose_action(14, np.array([4.0, 0.1]), dynamics, table, 0), [5.0, 0.25]
    )
    np.testing.assert_allclose(compose_action(0, None, dynamics, table, 99), table[0, -1])

    config = EgoEnvConfig(
        env=EnvConfig(episode_steps=6), traffic=TINY_TRAFFIC, scenes=1,
        maneuver_actions=True, action_repeat=2,
    )  # fmt: skip
    env = build_env(config, seed=0)
    assert env.action_space.n == len(table) == 15
    env.reset(seed=0)
    env.step(14)
    np.testing.assert_allclose(env.unwrapped.parallel_env.scene.last_action[0], table[14, 1])

    class Choosing:  # picks maneuver 3, then 7
        picks = iter([3, 7])

        def predict(self, observation, deterministic=True):
            return np.int64(next(self.picks)), None

    planner = PPOPlanner(Choosing(), action_repeat=2, maneuver_actions=True)
    planner.reset(None)
    actions = [planner(np.zeros(3)) for _ in range(4)]
    np.testing.assert_allclose(actions, [table[3, 0], table[3, 1], table[7, 0], table[7, 1]])


def test_linear_curriculum_ramps_then_holds():
    curriculum = LinearCurriculum(
        AdversaryStage(1, 10.0, "others"), AdversaryStage(5, 50.0, "ego"), ramp_fraction=0.5
    )
    assert curriculum.stage_at(0.0) == AdversaryStage(1, 10.0, "others")
    middle = curriculum.stage_at(0.25)
    assert middle.k == 3 and middle.lambda_adv == pytest.approx(30.0) and middle.target == "ego"
    assert curriculum.stage_at(0.5) == curriculum.stage_at(1.0) == AdversaryStage(5, 50.0, "ego")
    assert LinearCurriculum(AdversaryStage(1), AdversaryStage(5), 0.0).stage_at(0.0).k == 5
    with pytest.raises(ValueError, match="ramp_fraction"):
        LinearCurriculum(AdversaryStage(), AdversaryStage(), ramp_fraction=1.5)


def test_stage_validation():
    with pytest.raises(ValueError, match="target"):
        AdversaryStage(target="nobody")
    with pytest.raises(ValueError, match="k must be"):
        AdversaryStage(k=-1)
    with pytest.raises(ValueError, match="kind"):
        ScenePolicyConfig(kind="recorded")


def test_training_env_normalised_actions_outcome_and_stage():
    env = build_env(
        EgoEnvConfig(env=EnvConfig(episode_steps=5), traffic=TINY_TRAFFIC, scenes=2), seed=0
    )
    assert env.action_space.shape == (2,) and env.action_space.high.tolist() == [1.0, 1.0]
    env.set_adversary_stage(AdversaryStage(k=4, lambda_adv=20.0, target="ego"))
    adversary = env.unwrapped.policy
    assert adversary.k == 4 and adversary.guidance.lambda_adv == 20.0
    assert adversary.guidance.target == "ego" and adversary.guidance.steps == 2
    env.reset(seed=0)
    done, info = False, {}
    while not done:
        _, reward, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        done = terminated or truncated
        assert np.isfinite(reward)
    assert info["ego_collision"] in (0.0, 1.0) and info["ego_offroad"] in (0.0, 1.0)


def test_apply_stage_rejects_traffic_without_adversary():
    from riskflow_env.agents.idm import IDMPolicy

    with pytest.raises(TypeError, match="RiskFlow adversary"):
        apply_stage(IDMPolicy(), AdversaryStage())


@pytest.mark.parametrize("shards", ["1", "2"])
def test_train_on_the_batched_vector_env(tmp_path, shards):
    """``--vec-env batched``: the scenes in one EgoVectorEnv (or, with ``--shards 2``, one
    per worker process), the adversary planning them in one call; the curriculum and the
    outcome logging work through it."""
    run_dir = tmp_path / "batched"
    out = run(
        "train_ego_ppo.py", "--total-timesteps", "128", "--n-steps", "32", "--batch-size", "64",
        "--n-epochs", "1", "--num-envs", "2", "--vec-env", "batched", "--scenes", "3",
        "--episode-steps", "20", "--guidance-steps", "2", "--checkpoint-every", "0",
        "--seed", "3", "--device", "cpu", "--shards", shards, "--out", run_dir,
    )  # fmt: skip
    assert "final model" in out
    assert json.loads((run_dir / "options.json").read_text())["device"] == "cpu"
    assert (run_dir / "final_model.zip").is_file()
    assert (run_dir / "final_model_vecnormalize.pkl").is_file()
    header = (run_dir / "progress.csv").read_text().splitlines()[0].split(",")
    assert "curriculum/k" in header and "rollout/ego_collision_rate" in header


def test_adversary_device_is_checked_and_reaches_the_traffic():
    config = dataclasses.replace(ScenePolicyConfig(guidance_steps=1), device="cpu")
    assert str(make_traffic(config).device) == "cpu"
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: --device cuda is valid here")
    command = [sys.executable, str(ROOT / "examples" / "train_ego_ppo.py"), "--device", "cuda"]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert done.returncode != 0 and "--device cuda: CUDA is not available" in done.stderr


def test_train_then_evaluate_tiny_budget(tmp_path):
    run_dir = tmp_path / "run"
    out = run(
        "train_ego_ppo.py", "--total-timesteps", "256", "--n-steps", "64", "--batch-size", "64",
        "--n-epochs", "1", "--num-envs", "2", "--vec-env", "dummy", "--scenes", "3",
        "--episode-steps", "20", "--guidance-steps", "2", "--checkpoint-every", "128",
        "--seed", "3", "--base-planner", "lane", "--risk-reward", "-0.5", "--out", run_dir,
    )  # fmt: skip
    assert "final model" in out
    for name in ("initial_model", "final_model"):
        assert (run_dir / f"{name}.zip").is_file()
        assert (run_dir / f"{name}_vecnormalize.pkl").is_file()
    assert sorted(p.name for p in (run_dir / "checkpoints").glob("*.zip")) == [
        "ppo_128_steps.zip", "ppo_256_steps.zip"
    ]  # fmt: skip
    header = (run_dir / "progress.csv").read_text().splitlines()[0].split(",")
    assert "curriculum/k" in header and "rollout/ego_collision_rate" in header
    options = json.loads((run_dir / "options.json").read_text())
    assert options["base_planner"] == "lane" and options["risk_reward"] == -0.5

    eval_dir = tmp_path / "eval"
    out = run(
        "evaluate_ego.py", "--runs", run_dir, "--scenes", "2", "--seeds", "0",
        "--episode-steps", "10", "--guidance-steps", "2", "--planning-interval", "1.0",
        "--oracle", "--paired", "--out", eval_dir, "--trust-model",
    )  # fmt: skip
    results = json.loads((eval_dir / "results.json").read_text())
    rows = {(row["planner"], row["traffic"]) for row in results["summary"]}
    planners = ("ppo", "ppo-initial", "idm", "lane_keeping", "sampling_mpc", "constant_velocity")
    planners += ("random",)
    planners += ("oracle",)  # --oracle
    assert rows == {(p, t) for p in planners for t in ("riskflow K=5", "riskflow K=0")}
    assert all(row["ego_collision_rate"]["n"] == 2 for row in results["summary"])
    assert {row["planner"] for row in results["per_run"]} == {
        "ppo (seed 3)",
        "ppo-initial (seed 3)",
    }
    paired = results["paired"]  # trained vs untrained on the same episodes
    assert {(row["traffic"], row["metric"]) for row in paired} == {
        (t, m) for t in ("riskflow K=5", "riskflow K=0") for m in PAIRED_OUTCOMES
    }
    assert all(row["n"] == 2 and row["run"] == "seed 3" for row in paired)
    assert "Trained vs untrained, paired episodes" in (eval_dir / "results.md").read_text()
    versus = [row for row in paired if "reference" in row]  # --paired: each baseline too
    assert {row["reference"] for row in versus} == set(planners[2:])
    assert {row["planner"] for row in versus} == {f"ppo vs {name}" for name in planners[2:]}
    text = (eval_dir / "results.md").read_text()
    assert "Trained vs each baseline, paired episodes" in text
    assert "| trained - baseline [95% CI] |" in text
    assert (eval_dir / "results.png").stat().st_size > 0
    assert (eval_dir / "training.png").stat().st_size > 0  # the run's training curves
    assert "| ppo | riskflow K=5 |" in (eval_dir / "results.md").read_text()


def test_paired_counts_and_difference():
    from scipy import stats

    def records(outcomes):
        return [
            SimpleNamespace(scenario=SimpleNamespace(name=f"s{i}"), metrics=m)
            for i, m in enumerate(outcomes)
        ]

    hit = {"ego_collided": True, "ego_offroad": False}
    off = {"ego_collided": False, "ego_offroad": True}
    safe = {"ego_collided": False, "ego_offroad": False}
    untrained = records([hit] * 6 + [off] * 2 + [safe] * 2)
    trained = records([hit] * 2 + [safe] * 4 + [off, hit] + [safe] * 2)
    counts = paired_counts(trained, untrained, "ego_collision_rate")
    assert counts == {"n": 10, "trained": 3, "untrained": 6, "trained_only": 1, "untrained_only": 4}
    failures = paired_counts(trained, untrained, "ego_failure_rate")
    assert (failures["trained"], failures["untrained"]) == (4, 8)
    d = paired_difference(counts)
    assert d["difference"] == pytest.approx(-0.3)
    # Agresti-Min: 1/2 added to each cell, n* = 12, centre (1 - 4) / 12
    half = stats.norm.ppf(0.975) * np.sqrt(1 + 4 + 1 - 9 / 12) / 12
    assert (d["low"], d["high"]) == pytest.approx((-0.25 - half, -0.25 + half))
    none_discordant = paired_difference({**counts, "trained_only": 0, "untrained_only": 0})
    assert none_discordant["low"] < 0 < none_discordant["high"]  # not shrunk to a point
    all_one_way = paired_difference({**counts, "n": 2, "trained_only": 2, "untrained_only": 0})
    assert all_one_way["difference"] == 1 and all_one_way["high"] == 1  # clipped to [-1, 1]
    assert d["p_value"] == pytest.approx(stats.binomtest(1, 5, 0.5).pvalue)
    assert paired_difference({**counts, "trained_only": 0, "untrained_only": 0})["p_value"] == 1
    with pytest.raises(ValueError, match="metric"):
        paired_counts(trained, untrained, "progress")
    with pytest.raises(ValueError, match="same episodes"):
        paired_counts(trained[::-1], untrained, "ego_collision_rate")


def test_adversary_reward_terms():
    config = AdversaryRewardConfig()
    info = {"collided_with": ["ego", "agent_2"], "offroad_fraction": 0.0}
    reward, terms = adversary_reward(info, 0.0, config)
    assert terms == {"ego_collision": 5.0, "other_collision": -1.0, "closeness": 0.05,
                     "offroad": 0.0}  # fmt: skip
    assert reward == pytest.approx(4.05)
    far, terms = adversary_reward({"collided_with": [], "offroad_fraction": 0.2}, 45.0, config)
    assert terms["closeness"] == 0.0 and far == -1.0
