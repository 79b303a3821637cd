"""Train an ego with Stable-Baselines3 PPO against the RiskFlow adversary (``rl`` extra).

    python examples/train_ego_ppo.py --seed 0 --vec-env dummy --out runs/ego_ppo/seed0

Results and the documented runs: docs/tutorials/rl-ego.md, docs/explanation/rl-results.md.
The adversary is the evaluation's (30 guidance steps, a re-plan every 0.5 s): most of a step.

The ego drives ``RiskFlowEgo-v0`` (:class:`~policies.rl.envs.EgoTrainingEnv`); the RiskFlow
adversary drives every other vehicle, with a curriculum that ramps ``k`` and the guidance
weight ``lambda_adv`` (and optionally switches the target) over the first
``ramp_fraction`` of training (:mod:`policies.rl.curriculum`). Episodes come from the
shipped *training* bank; evaluate on the evaluation bank with ``examples/evaluate_ego.py``.

The defaults: every 0.2 s (``--action-repeat 2``) the policy picks one of 15 maneuvers
(brake / hold / accelerate, each straight, as a lane change or a turn either way;
``--maneuver-actions``), added to lane keeping (``--base-planner lane``), seeing besides
the env's observation what each maneuver would lead to under constant-velocity
predictions of the others (``--maneuver-features``; :mod:`policies.rl.features`).
``--no-maneuver-actions --no-maneuver-features --action-repeat 1`` gives the continuous
policy (normalised (accel, yaw rate), 0 = keep speed and heading), with
``--base-planner none`` (the policy drives), ``idm`` (a residual over IDM) or ``lane``.

Reward: the env's (``RewardConfig``) with collision and off-road at -10 (library: -5): the
speed term pays at most 0.1 per step (``--speed-reward``, at ``--target-speed`` 25 m/s), so
avoiding one collision is worth 100 steps at full speed, and leaving the road is never a
cheaper way out of a crash than the crash (both end the episode).

Writes to ``--out`` (:mod:`policies.rl.runs`): ``options.json``; ``initial_model.zip``
(the untrained policy) and ``final_model.zip``, each with its ``*_vecnormalize.pkl``
observation statistics; ``checkpoints/`` every ``--checkpoint-every`` decisions and at
the end; ``progress.csv`` (SB3's CSV log: returns, losses, ``rollout/ego_collision_rate``,
``curriculum/*``), ``training.png`` (the curves) and TensorBoard files with ``--tensorboard``.

Ctrl-C or SIGTERM saves a checkpoint as of the last update and exits with one line (status
130 / 143); ``--resume RUN`` goes on from it, bit for bit but for the episodes in flight,
which start afresh (:mod:`policies.rl.checkpoints`).
"""

from __future__ import annotations

import dataclasses
import json
import signal
import sys
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import CallbackList
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import (
    DummyVecEnv,
    SubprocVecEnv,
    VecEnv,
    VecMonitor,
    VecNormalize,
)

from policies.cli_inputs import check_device
from policies.dataclass_cli import check_at_least, check_between, check_choices
from policies.learned.adversary_config import check_planning_interval
from policies.rl.adversary import TARGETS, AdversaryStage, ScenePolicyConfig
from policies.rl.checkpoints import (
    RunCheckpoints,
    keep_progress_rows,
    restore_progress_rows,
    resume,
    save_model,
)
from policies.rl.curriculum import CurriculumCallback, LinearCurriculum, OutcomeCallback
from policies.rl.envs import BASE_PLANNERS, EgoEnvConfig, interface_options, make_env
from policies.rl.features import MANEUVER_SETS
from policies.rl.progress import StepProgressBar
from policies.rl.report import plot_training
from policies.rl.runs import (
    Checkpoint,
    RunError,
    checkpoint_files,
    final_from_checkpoint,
    latest_checkpoint,
    make_run_folder,
    parse_resumable,
)
from policies.rl.sb3_shards import ShardedEgoVecEnv
from policies.rl.sb3_vec_env import sb3_ego_vec_env
from policies.rl.signals import StopSignals, exit_stopped
from policies.rl.vector_env import build_vector_env
from riskflow_env.config import EnvConfig, RewardConfig
from riskflow_env.scenarios import SPLITS, shipped_bank

VEC_ENVS = ("subproc", "dummy", "batched")
RESUMABLE = ("total_timesteps", "checkpoint_every")  # what --resume lets change
TRAFFICS = ("riskflow", "idm")  # what --traffic trains against (log replay does not react)


@dataclass(frozen=True)
class Options:
    """Options of train_ego_ppo.py."""

    total_timesteps: int = 80_000
    """env steps to train for (all envs together)"""
    seed: int = 0
    """seeds PPO, torch, numpy, the scene draws and the adversary's noise"""
    out: Path = Path("runs/ego_ppo/seed0")
    """output folder"""
    num_envs: int = 2
    """parallel envs (one adversary each; with --vec-env batched: scenes of one vector env)"""
    vec_env: str = "subproc"
    """'subproc' (one process per env), 'dummy' (all in this process; tests) or 'batched'
    (policies.rl.EgoVectorEnv: the scenes stepped together, one adversary planning them all
    in one call)"""
    shards: int = 1
    """with --vec-env batched: split the scenes over this many worker processes, each one
    vector env (policies.rl.sb3_shards; one per core: 2 on a 2-core machine)"""
    split: str = "train"
    """shipped scenario bank the episodes come from"""
    scenes: int | None = None
    """use only the first N scenes of the split (None: all)"""
    episode_steps: int = 100
    """episode length [steps of 0.1 s]"""
    base_planner: str = "lane"
    """'none' (the policy drives), 'idm' (the policy's action is added to IDM's: residual) or
    'lane' (added to lane keeping at constant speed: the policy owns the acceleration)"""
    action_repeat: int = 2
    """env steps per policy decision (the action is held; the base planner steers every
    step); ``total_timesteps`` counts decisions, i.e. env steps / action_repeat"""
    maneuver_features: bool = True
    """append what 15 fixed maneuvers would lead to (predicted clearance and road margin,
    constant-velocity predictions; policies.rl.features) to the observation"""
    maneuver_set: str = "compact"
    """the maneuvers of --maneuver-features and --maneuver-actions: 'compact' (15) or 'mpc'
    (the sampling MPC's 200 candidates, finer accelerations, turns and lane changes)"""
    maneuver_actions: bool = True
    """discrete actions: choose one of the 15 maneuvers of policies.rl.features.maneuvers
    (brake / hold / accelerate x straight / lane change / turn) every --action-repeat steps
    (--log-std-init and gSDE do not apply)"""
    use_sde: bool = False
    """generalized state-dependent exploration (gSDE; Raffin et al. 2022): noise that is
    constant over ``sde_sample_freq`` steps instead of fresh every step"""
    sde_sample_freq: int = -1
    """resample the gSDE noise every N decisions (-1: once per rollout)"""
    traffic: str = "riskflow"
    """the other vehicles' driver: 'riskflow' (the adversary, ramped by the curriculum
    options below; --k-start 0 --k-end 0 is the unguided generator) or 'idm' (IDM traffic,
    no adversary: the curriculum options do not apply)"""
    guidance_steps: int = 30
    """K_g of the training adversary (the evaluation's; 10 trains a cheaper, weaker one)"""
    planning_interval: float = 0.5
    """re-plan interval of the training adversary [s] (the evaluation's)"""
    k_start: int = 1
    """curriculum: controllable vehicles at the start"""
    k_end: int = 5
    """curriculum: controllable vehicles after the ramp"""
    lambda_adv_start: float = 10.0
    """curriculum: adversarial guidance weight at the start [1/m]"""
    lambda_adv_end: float = 50.0
    """curriculum: adversarial guidance weight after the ramp [1/m]"""
    target_start: str = "others"
    """curriculum: guidance target at the start ('others' or 'ego')"""
    target_end: str = "others"
    """curriculum: guidance target from half-way through the ramp"""
    ramp_fraction: float = 0.2
    """share of training the curriculum ramp takes (0: no curriculum)"""
    speed_reward: float = 0.1
    """weight of the speed term, ``speed_reward * min(v, target_speed) / target_speed``"""
    target_speed: float = 25.0
    """speed at which the speed term saturates [m/s]"""
    collision_reward: float = -10.0
    """reward when the ego collides [per step]"""
    offroad_reward: float = -10.0
    """reward while the ego is off the road [per step]"""
    terminate_on_offroad: bool = True
    """end the episode when the ego leaves the road (the library default); off: it pays
    ``offroad_reward`` every step it is off, so leaving the road never ends its troubles"""
    risk_reward: float = -0.05
    """weight of the TTC risk term (times the ego's largest TTC risk weight, in [0, 1])"""
    n_steps: int = 512
    """PPO rollout length per env"""
    batch_size: int = 128
    """PPO minibatch size"""
    n_epochs: int = 10
    """PPO epochs per update"""
    learning_rate: float = 3e-4
    """Adam learning rate"""
    gamma: float = 0.97
    """discount factor"""
    log_std_init: float = -1.2
    """initial log std of the Gaussian policy (normalised actions; -1.2: std 0.30)"""
    normalize: bool = True
    """normalise observations and rewards (VecNormalize; stats saved with each model)"""
    checkpoint_every: int = 20_000
    """save a resumable checkpoint every N decisions, at the first update after each multiple
    (0: none; the end of training and Ctrl-C / SIGTERM always save one)"""
    resume: Path | None = None
    """continue the run in this folder from its latest checkpoint, with its options.json
    (only --total-timesteps and --checkpoint-every may change)"""
    tensorboard: bool = False
    """also write TensorBoard event files to <out>/tb"""
    device: str = "cpu"
    """torch device of the adversary ('cuda' where a GPU is present: with --vec-env batched
    and many --num-envs, its planning calls are large); PPO's small MLP stays on the CPU"""

    def __post_init__(self) -> None:
        if self.maneuver_actions and self.use_sde:
            raise ValueError("--use-sde needs continuous actions: drop --maneuver-actions")
        check_choices(self, {"vec_env": VEC_ENVS, "maneuver_set": MANEUVER_SETS, "split": SPLITS})
        check_choices(self, {"traffic": TRAFFICS, "base_planner": BASE_PLANNERS})
        check_choices(self, {"target_start": TARGETS, "target_end": TARGETS})
        counts = ("total_timesteps", "num_envs", "n_steps", "n_epochs", "action_repeat", "shards")
        nonnegative = ("seed", "k_start", "k_end", "guidance_steps", "checkpoint_every")
        lows = dict.fromkeys((*counts, "episode_steps", "scenes"), 1) | {"batch_size": 2}
        check_at_least(self, lows | dict.fromkeys(nonnegative, 0), optional=("scenes",))
        if self.n_steps * self.num_envs < 2 or self.seed >= 2**32:  # SB3's own bounds
            raise ValueError("--n-steps x --num-envs must be >= 2 and --seed < 2**32")
        if (self.scenes or 0) > (bank := len(shipped_bank(self.split))):
            raise ValueError(f"--scenes: {self.split} has {bank} scenes, got {self.scenes}")
        check_planning_interval(self.planning_interval)
        if self.shards > 1 and self.vec_env != "batched" or self.shards > self.num_envs:
            raise ValueError(f"--shards {self.shards} needs --vec-env batched, as many --num-envs")
        check_device(self.device)
        up, al = (0.0, float("inf")), (-float("inf"), float("inf"))
        check_between(self, dict(target_speed=up, learning_rate=up, gamma=(0, 1), log_std_init=al))
        check_between(self, {f"{n}_reward": al for n in ("speed", "collision", "offroad", "risk")})
        if not (self.lambda_adv_start >= 0 and self.lambda_adv_end >= 0):
            raise ValueError("--lambda-adv-start and --lambda-adv-end must be >= 0")
        if not 0 <= self.ramp_fraction <= 1:
            raise ValueError(f"--ramp-fraction must be in [0, 1], got {self.ramp_fraction}")


def env_config(options: Options) -> EgoEnvConfig:
    """The workers' env: training bank, cheaper adversary, reward weights of the options."""
    reward = RewardConfig(
        target_speed=options.target_speed,
        speed=options.speed_reward,
        collision=options.collision_reward,
        offroad=options.offroad_reward,
        risk=options.risk_reward,
    )
    start = AdversaryStage(options.k_start, options.lambda_adv_start, options.target_start)
    return EgoEnvConfig(
        env=EnvConfig(
            episode_steps=options.episode_steps,
            reward=reward,
            terminate_on_offroad="ego" if options.terminate_on_offroad else "none",
        ),
        traffic=ScenePolicyConfig(
            kind=options.traffic,
            stage=start,
            guidance_steps=options.guidance_steps,
            planning_interval=options.planning_interval,
            device=options.device,
        ),
        split=options.split,
        scenes=options.scenes,
        **interface_options(options),
    )


def build_vec_env(options: Options, config: EgoEnvConfig) -> VecEnv:
    """The training envs of ``options.vec_env`` (VecNormalize is added by the caller)."""
    if options.vec_env == "batched" and options.shards > 1:  # the same scenes, per core
        return VecMonitor(
            ShardedEgoVecEnv(config, options.num_envs, options.shards, seed=options.seed)
        )
    if options.vec_env == "batched":  # scene b is make_env's rank b, stepped together
        return sb3_ego_vec_env(build_vector_env(config, options.num_envs, options.seed))
    factories = [make_env(config, rank, options.seed) for rank in range(options.num_envs)]
    return (SubprocVecEnv if options.vec_env == "subproc" else DummyVecEnv)(factories)


def new_model(options: Options, env: VecEnv) -> PPO:
    """An untrained PPO of the options."""
    if options.normalize:
        env = VecNormalize(env, norm_obs=True, norm_reward=True, clip_obs=10.0)
    return PPO(
        "MlpPolicy",
        env,
        n_steps=options.n_steps,
        batch_size=options.batch_size,
        n_epochs=options.n_epochs,
        learning_rate=options.learning_rate,
        gamma=options.gamma,
        policy_kwargs={} if options.maneuver_actions else {"log_std_init": options.log_std_init},
        use_sde=options.use_sde,
        sde_sample_freq=options.sde_sample_freq,
        seed=options.seed,
        device="cpu",
        verbose=0,
    )


def resumed_model(options: Options, env: VecEnv, checkpoint: Checkpoint) -> PPO:
    """The PPO of ``checkpoint`` on ``env`` (policies.rl.checkpoints.resume)."""
    if checkpoint.stats is not None:
        env = VecNormalize.load(str(checkpoint.stats), env)
    try:
        model = PPO.load(checkpoint.model, env=env, device="cpu")
    except ValueError as error:  # SB3: the saved spaces differ from the env's
        raise RunError(
            f"--resume {options.out}: {checkpoint.model} does not fit ({error})"
        ) from None
    resume(model, checkpoint, options.seed)
    return model


class TrainingInterrupted(Exception):
    """SIGINT or SIGTERM stopped training; ``checkpoint`` holds where it stopped."""

    def __init__(self, checkpoint: Path, signum: int) -> None:
        super().__init__(checkpoint, signum)
        self.checkpoint, self.signum = checkpoint, signum


def train(options: Options) -> Path:
    """Train (or, with ``--resume``, go on training); returns the final model's path.
    Raises :class:`TrainingInterrupted` after saving a checkpoint on SIGINT / SIGTERM."""
    out = options.out
    checkpoint = latest_checkpoint(out) if options.resume is not None else None
    if checkpoint is not None and checkpoint.decisions >= options.total_timesteps:
        print(f"{out} has trained {checkpoint.decisions} decisions (raise --total-timesteps)")
        return final_from_checkpoint(out, checkpoint)
    if options.resume is None:
        make_run_folder(out)
    elif checkpoint is None:
        print(f"{out} has no checkpoint yet: training from the start")
    (out / "options.json").write_text(json.dumps(dataclasses.asdict(options), default=str))
    set_random_seed(options.seed)
    config = env_config(options)
    formats = ["csv", "stdout"] + (["tensorboard"] if options.tensorboard else [])
    # closed on every way out: workers ignore SIGTERM, so an open one would hang the exit
    with closing(build_vec_env(options, config)) as env:
        if checkpoint is None:
            model = new_model(options, env)
            model.set_logger(configure(str(out), formats))
            save_model(model, out / "initial_model")
        else:
            model = resumed_model(options, env, checkpoint)
            kept = keep_progress_rows(out / "progress.csv", checkpoint.decisions)
            model.set_logger(configure(str(out), formats))
            restore_progress_rows(model.logger, kept)
            print(f"resuming {out} at {checkpoint.decisions} decisions ({checkpoint.model.name})")

        curriculum = LinearCurriculum(
            start=config.traffic.stage,
            end=AdversaryStage(options.k_end, options.lambda_adv_end, options.target_end),
            ramp_fraction=options.ramp_fraction,
        )
        with StopSignals() as stop:
            checkpoints = RunCheckpoints(out / "checkpoints", options.checkpoint_every, stop)
            ramp = [CurriculumCallback(curriculum, options.total_timesteps)]
            callbacks = [
                *(ramp if options.traffic == "riskflow" else []),  # IDM traffic has no stages
                OutcomeCallback(),
                StepProgressBar(options.total_timesteps, "PPO ego"),
                checkpoints,
            ]
            remaining = options.total_timesteps - model.num_timesteps
            model.learn(remaining, callback=CallbackList(callbacks), reset_num_timesteps=False)
            if stop.received is None:
                save_model(model, out / "final_model")
    plot_training({f"seed {options.seed}": out}, out / "training.png")
    if stop.received is not None:
        raise TrainingInterrupted(checkpoints_of(checkpoints), stop.received)
    return out / "final_model.zip"


def checkpoints_of(callback: RunCheckpoints) -> Path:
    """The checkpoint the stop wrote (or the last one before it)."""
    return checkpoint_files(callback.folder, callback.saved or 0)[0]


def parse(argv: list[str] | None) -> Options:
    """The options; with ``--resume RUN``, the run's own (only ``--total-timesteps`` and
    ``--checkpoint-every`` may change), or a usage error naming what is wrong."""
    return parse_resumable(Options, argv, "train_ego_ppo.py", __doc__, RESUMABLE)


def main(argv: list[str] | None = None) -> None:
    options = parse(argv)
    try:
        path = train(options)
    except TrainingInterrupted as stop:
        exit_stopped(
            stop.signum,
            f"train_ego_ppo.py: stopped by {{name}}; checkpoint {stop.checkpoint}; continue "
            f"with: python examples/train_ego_ppo.py --resume {options.out}",
        )
    except RunError as error:
        print(f"train_ego_ppo.py: error: {error}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("train_ego_ppo.py: interrupted before training started", file=sys.stderr)
        sys.exit(128 + signal.SIGINT)
    print(f"final model: {path}")


if __name__ == "__main__":
    main()
