"""An ego trained with TorchRL PPO against the RiskFlow adversary (the ``torchrl`` extra).

    python examples/train_ego_torchrl.py --iterations 20 --out runs/ego_torchrl

The env is the SB3 recipe's (:func:`policies.rl.envs.build_env`: the ego picks one of 15
maneuvers every 0.2 s over lane keeping and sees their predicted clearance; the RiskFlow
adversary, ``--k`` guided vehicles with ``--guidance-steps`` per plan, drives the others)
in TorchRL's ``GymWrapper``. The action mask of ``info["action_mask"]`` (maneuvers that
keep the ego on the road) reaches the tensordict through an info reader, and the policy
samples a ``MaskedCategorical`` over it; TorchRL's ``ActionMask`` transform applies it to
random actions. ``VecNormV2`` normalises the observations; ``ClipPPOLoss`` with ``GAE``.

Per iteration it collects ``--frames-per-batch`` decisions and prints the decisions so
far, the mean reward per decision and the finished episodes' mean return; it writes
``<out>/checkpoint.pt`` (policy, value, optimiser, observation statistics, iteration:
tensors only, loaded with ``weights_only=True``) and ``<out>/progress.json`` every
``--checkpoint-every`` iterations, at the end and on Ctrl-C / SIGTERM (one line, status
130 / 143); ``--resume`` goes on from them up to ``--iterations`` (the episodes in flight
start afresh).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from riskflow_env.cli_errors import missing_extra

try:  # the torchrl extra
    from tensordict.nn import TensorDictModule
    from torchrl.collectors import Collector
    from torchrl.data import Binary, LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
    from torchrl.envs import ActionMask, Compose, GymWrapper, RewardSum, TransformedEnv, VecNormV2
    from torchrl.envs.libs.gym import default_info_dict_reader
    from torchrl.modules import MLP, MaskedCategorical, ProbabilisticActor, ValueOperator
    from torchrl.objectives import ClipPPOLoss
    from torchrl.objectives.value import GAE
except ModuleNotFoundError as error:
    raise SystemExit(missing_extra("train_ego_torchrl.py", "torchrl", error.name)) from None

from policies.dataclass_cli import check_at_least, parse_dataclass
from policies.rl.adversary import AdversaryStage, ScenePolicyConfig
from policies.rl.envs import EgoEnvConfig, build_env
from policies.rl.runs import check_resume
from policies.rl.signals import StopSignals, exit_stopped
from riskflow_env.atomic_files import atomic_file, write_text
from riskflow_env.config import EnvConfig


@dataclass(frozen=True)
class Options:
    """Options of train_ego_torchrl.py."""

    iterations: int = 20
    """PPO iterations (each collects --frames-per-batch decisions)"""
    frames_per_batch: int = 1024
    """decisions collected per iteration"""
    epochs: int = 4
    """passes over each batch"""
    minibatch: int = 128
    """decisions per gradient step"""
    learning_rate: float = 3e-4
    """Adam learning rate"""
    gamma: float = 0.97
    """discount per decision"""
    seed: int = 0
    """seeds torch, the scene draws and the adversary's noise"""
    scenes: int | None = None
    """use only the first N scenes of the training bank (None: all)"""
    episode_steps: int = 100
    """episode length [steps of 0.1 s]"""
    k: int = 5
    """vehicles the adversary guides toward a collision"""
    guidance_steps: int = 10
    """guidance gradient steps per plan (the default adversary: 30)"""
    planning_interval: float = 1.0
    """[s] re-planning interval of the adversary"""
    checkpoint_every: int = 5
    """write the checkpoint and progress.json every N iterations (0: at the end and on a
    stop signal only)"""
    resume: bool = False
    """continue the run in --out from its checkpoint.pt and progress.json"""
    out: Path = Path("runs/ego_torchrl")
    """output folder"""

    def __post_init__(self) -> None:
        counts = ("iterations", "frames_per_batch", "epochs", "minibatch", "episode_steps")
        check_at_least(self, dict.fromkeys(counts, 1) | {"checkpoint_every": 0})
        if self.minibatch > self.frames_per_batch:
            raise ValueError("--minibatch must be <= --frames-per-batch")
        check_resume(self.out / "checkpoint.pt", self.resume)


def make_env(options: Options, seed: int) -> TransformedEnv:
    """The recipe's ego env in TorchRL, with the action mask and observation statistics;
    its scene draws and adversary noise seeded with ``seed``."""
    config = EgoEnvConfig(
        env=EnvConfig(episode_steps=options.episode_steps),
        traffic=ScenePolicyConfig(
            stage=AdversaryStage(k=options.k),
            guidance_steps=options.guidance_steps,
            planning_interval=options.planning_interval,
        ),
        scenes=options.scenes,
        base_planner="lane",
        action_repeat=2,
        maneuver_features=True,
        maneuver_actions=True,
    )
    gym_env = build_env(config, seed=seed)
    env = GymWrapper(gym_env, categorical_action_encoding=True, device="cpu")
    count = gym_env.action_space.n
    spec = {"action_mask": Binary(n=count, shape=(count,), dtype=torch.bool)}
    env.set_info_dict_reader(default_info_dict_reader(["action_mask"], spec=spec))
    env = TransformedEnv(
        env, Compose(ActionMask(), VecNormV2(in_keys=["observation"]), RewardSum())
    )
    env.set_seed(seed)
    return env


def make_modules(env: TransformedEnv) -> tuple[ProbabilisticActor, ValueOperator]:
    """Policy (logits -> MaskedCategorical over the action mask) and value networks."""
    size = env.observation_spec["observation"].shape[-1]
    count = env.action_spec.space.n
    logits = TensorDictModule(
        MLP(in_features=size, out_features=count, num_cells=[64, 64], activation_class=nn.Tanh),
        in_keys=["observation"],
        out_keys=["logits"],
    )
    actor = ProbabilisticActor(
        logits,
        in_keys={"logits": "logits", "mask": "action_mask"},
        distribution_class=MaskedCategorical,
        spec=env.action_spec,
        return_log_prob=True,
    )
    value = ValueOperator(
        MLP(in_features=size, out_features=1, num_cells=[64, 64], activation_class=nn.Tanh),
        in_keys=["observation"],
    )
    return actor, value


def save(path: Path, modules: dict[str, nn.Module], optimiser, history: list[dict]) -> None:
    """``checkpoint.pt`` (state dicts and the iteration) and ``progress.json`` in ``path``."""
    path.mkdir(parents=True, exist_ok=True)
    state = {name: module.state_dict() for name, module in modules.items()}
    state |= {"optimiser": optimiser.state_dict(), "iteration": torch.tensor(len(history))}
    with atomic_file(path / "checkpoint.pt") as file:
        torch.save(state, file)
    write_text(path / "progress.json", json.dumps(history, indent=1))


def train(options: Options) -> list[dict]:
    """Train (or go on training); the per-iteration rows. Exits with one line on a stop."""
    done = 0  # decisions of the iterations already run (--resume)
    if options.resume:
        done = len(json.loads((options.out / "progress.json").read_text()))
        done *= options.frames_per_batch
    torch.manual_seed(options.seed + done)  # a resume: fresh episodes, new draws
    env = make_env(options, options.seed + done)
    actor, value = make_modules(env)
    actor(env.reset())  # materialise the lazy parts before loading or optimising
    loss = ClipPPOLoss(actor, value, clip_epsilon=0.2, entropy_coeff=0.01)
    advantage = GAE(gamma=options.gamma, lmbda=0.95, value_network=value)
    optimiser = torch.optim.Adam(loss.parameters(), lr=options.learning_rate)
    modules = {"actor": actor, "value": value, "vecnorm": env.transform[1]}
    history: list[dict] = []
    if options.resume:
        state = torch.load(options.out / "checkpoint.pt", weights_only=True)
        for name, module in modules.items():
            module.load_state_dict(state[name])
        optimiser.load_state_dict(state["optimiser"])
        history = json.loads((options.out / "progress.json").read_text())
        print(f"resuming {options.out} after iteration {len(history)}")
    remaining = options.iterations - len(history)
    collector = Collector(env, actor, frames_per_batch=options.frames_per_batch,
                          total_frames=max(remaining, 0) * options.frames_per_batch,
                          auto_register_policy_transforms=False)  # fmt: skip
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(options.frames_per_batch),
        sampler=SamplerWithoutReplacement(),
        batch_size=options.minibatch,
    )
    with StopSignals() as stop:
        for batch in collector:
            with torch.no_grad():
                advantage(batch)
            buffer.extend(batch.reshape(-1))
            for _ in range(options.epochs * (options.frames_per_batch // options.minibatch)):
                terms = loss(buffer.sample())
                total = terms["loss_objective"] + terms["loss_critic"] + terms["loss_entropy"]
                optimiser.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optimiser.step()
            collector.update_policy_weights_()
            done = batch["next", "done"].squeeze(-1)
            returns = batch["next", "episode_reward"][done]
            row = {
                "iteration": len(history) + 1,
                "decisions": (len(history) + 1) * options.frames_per_batch,
                "reward_per_decision": batch["next", "reward"].mean().item(),
                "episodes": int(done.sum()),
                "episode_return_mean": returns.mean().item() if returns.numel() else None,
            }
            history.append(row)
            print(
                f"iteration {row['iteration']}: {row['decisions']} decisions, reward/decision "
                f"{row['reward_per_decision']:.3f}, {row['episodes']} episodes"
            )
            every = options.checkpoint_every
            if stop.received is not None or (every and row["iteration"] % every == 0):
                save(options.out, modules, optimiser, history)
            if stop.received is not None:
                break
    collector.shutdown()
    save(options.out, modules, optimiser, history)
    if stop.received is not None:
        exit_stopped(
            stop.received,
            f"train_ego_torchrl.py: stopped by {{name}} after iteration {len(history)}; "
            f"continue with --resume --out {options.out}",
        )
    return history


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(Options, argv, prog="train_ego_torchrl.py", description=__doc__)
    train(options)


if __name__ == "__main__":
    main()
