"""Closed-loop evaluation of ego planners (a trained PPO ego among them) against traffic.

:class:`PPOPlanner` turns a Stable-Baselines3 model (and the ``VecNormalize`` statistics
it was trained with) into an :class:`~policies.planners.EgoPlanner`; :class:`RandomPlanner`
draws uniform actions. :func:`evaluate` runs every planner against every traffic on the
same scenes and seeds through :class:`~policies.harness.ClosedLoop` (the harness of the
stress tests); :func:`summarize_ego` reduces the episodes to the ego's collision rate,
the rate of collisions it could have avoided, off-road rate, progress and time to first
collision with 95% intervals over all
(seed, scene) episodes: Wilson for rates, percentile bootstrap for means.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from policies.harness import ClosedLoop, EpisodeRecord, summarize
from policies.rl.adversary import ScenePolicyConfig, make_traffic
from policies.rl.envs import EgoInterface
from policies.statistics import mean_interval, mean_summary, per_km, rate
from policies.stress.failures import analyse
from policies.stress.summary import progress, slow_ego_steps
from riskflow_env.config import DynamicsConfig, EnvConfig
from riskflow_env.scenarios import Scenario
from riskflow_env.view import SceneView

PlannerFactory = Callable[[int], Any]  # seed -> EgoPlanner


class PPOPlanner:
    """A trained SB3 policy as an ego planner (normalised actions, see :func:`scale_action`).

    Args:
        model: an SB3 algorithm (``PPO.load(...)``) trained on
            :class:`~policies.rl.envs.EgoTrainingEnv`.
        normalize: the ``VecNormalize`` it was trained with (its observation statistics
            are applied), or None.
        deterministic: act with the mean of the Gaussian (True) or sample it.
        dynamics: the env's bounds (to de-normalise actions).
        mask_actions: with maneuver actions, choose only among the maneuvers the action
            mask allows (:meth:`~policies.rl.envs.EgoInterface.action_mask`: those that keep
            the ego's footprint on the road over the next second), the most probable one
            (or a draw from the policy's probabilities renormalised over them): a safety
            filter at deployment, as highway-env's available actions. False: the policy's
            own choice (the raw policy). Continuous actions have no mask.
        **interface: ``base_planner``, ``action_repeat``, ``maneuver_features``,
            ``maneuver_actions``, ``maneuver_set`` of
            :class:`~policies.rl.envs.EgoInterface`, as trained.
    """

    def __init__(
        self,
        model: Any,
        normalize: Any = None,
        deterministic: bool = True,
        dynamics: DynamicsConfig | None = None,
        mask_actions: bool = True,
        **interface: Any,
    ) -> None:
        self.model, self.normalize = model, normalize
        self.deterministic, self.mask_actions = deterministic, mask_actions
        self.interface = EgoInterface(dynamics or DynamicsConfig(), **interface)
        self._held: Any = None
        self._calls = 0

    def reset(self, view: SceneView) -> None:
        """Reset the base planner, if any, and the held action (the policy itself is a
        feed-forward MLP)."""
        self.interface.reset(view)
        self._held, self._calls = None, 0

    def __call__(self, observation: np.ndarray, view: SceneView | None = None) -> np.ndarray:
        """(2,) (accel [m/s^2], yaw rate [rad/s]) from the ego's observation (and the
        view, for the base planner and the features); the policy decides every
        ``action_repeat`` calls, as in training, and the base planner every call."""
        substep = self._calls % self.interface.action_repeat
        if substep == 0:
            seen = self.interface.observe(observation, view)
            if self.normalize is not None:
                seen = self.normalize.normalize_obs(seen)
            masked = self.mask_actions and view is not None  # the mask needs the scene
            allowed = self.interface.action_mask(view) if masked else None
            if allowed is None:
                self._held, _ = self.model.predict(seen, deterministic=self.deterministic)
            else:
                self._held = self._masked_choice(seen, allowed)
        self._calls += 1
        return self.interface.env_action(self._held, observation, view, substep)

    def _masked_choice(self, observation: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        """The maneuver index the policy chooses among the ``allowed`` (M,) ones."""
        policy = self.model.policy
        with torch.no_grad():
            tensor, _ = policy.obs_to_tensor(observation)
            logits = policy.get_distribution(tensor).distribution.logits[0]
            logits = logits.masked_fill(~torch.as_tensor(allowed, device=logits.device), -torch.inf)
            if self.deterministic:
                return np.array(int(torch.argmax(logits)))
            return np.array(int(torch.distributions.Categorical(logits=logits).sample()))


class RandomPlanner:
    """Uniform random actions over the dynamics bounds (a floor for every metric).

    Args:
        seed: seeds the draws (the same seed gives the same actions).
        dynamics: the bounds.
    """

    def __init__(self, seed: int = 0, dynamics: DynamicsConfig | None = None) -> None:
        self.rng = np.random.default_rng(seed)
        self.dynamics = dynamics or DynamicsConfig()

    def reset(self, view: SceneView) -> None:
        """Nothing to prepare."""

    def __call__(self, observation: np.ndarray, view: SceneView | None = None) -> np.ndarray:
        """(2,) uniform in [accel_min, accel_max] x [-yaw_rate_max, yaw_rate_max]."""
        d = self.dynamics
        return self.rng.uniform([d.accel_min, -d.yaw_rate_max], [d.accel_max, d.yaw_rate_max])


class UntrustedModelError(PermissionError):
    """Loading a pickled (code-executing) model file without ``trusted=True``."""


def load_ppo_planner(
    run: str,
    deterministic: bool = True,
    *,
    trusted: bool = False,
    mask_actions: bool = True,
    **interface: Any,
) -> PPOPlanner:
    """A :class:`PPOPlanner` from a model file (``.zip``) saved by ``train_ego_ppo.py``;

    **Security:** stable-baselines3 unpickles the model zip and the ``_vecnormalize.pkl``
    file, so loading them runs any code they contain. Load only files you (or someone
    you trust) wrote, and say so with ``trusted=True`` (``--trust-model`` in
    ``examples/evaluate_ego.py``); without it this raises :class:`UntrustedModelError`
    before reading anything (docs/reference/security.md).

    the ``VecNormalize`` statistics are read from the same name with ``_vecnormalize.pkl``
    in place of ``.zip`` (checkpoints: ``ppo_N_steps.zip`` -> ``ppo_vecnormalize_N_steps.pkl``)
    when that file exists. ``interface`` (:class:`PPOPlanner`'s) must be what the model
    was trained with; ``mask_actions`` as :class:`PPOPlanner`'s."""
    from pathlib import Path

    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    path = Path(run)
    if trusted is not True:
        raise UntrustedModelError(
            f"{path}: a stable-baselines3 model (and its _vecnormalize.pkl) is a pickle that "
            "can run arbitrary code when loaded; pass trusted=True (examples: --trust-model) "
            "only for files you trust (docs/reference/security.md)"
        )
    model = PPO.load(path, device="cpu")
    stem = path.name.removesuffix(".zip")
    stats = path.with_name(stem + "_vecnormalize.pkl")
    if stem.startswith("ppo_") and stem.endswith("_steps"):  # SB3's CheckpointCallback names
        stats = path.with_name("ppo_vecnormalize_" + stem.removeprefix("ppo_") + ".pkl")
    normalize = None
    if stats.is_file():
        normalize = VecNormalize.load(str(stats), venv=_DummyVec(model))
        normalize.training, normalize.norm_reward = False, False
    return PPOPlanner(model, normalize, deterministic, None, mask_actions, **interface)


class _DummyVec:
    """The minimum of a VecEnv that ``VecNormalize.load`` needs (spaces, num_envs)."""

    def __init__(self, model: Any) -> None:
        self.observation_space, self.action_space = model.observation_space, model.action_space
        self.num_envs, self.render_mode = 1, None


def evaluate(
    planners: dict[str, PlannerFactory],
    traffics: Sequence[ScenePolicyConfig],
    scenes: Sequence[Scenario],
    seeds: Sequence[int],
    config: EnvConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[tuple[str, str], list[EpisodeRecord]]:
    """Every planner against every traffic on every (seed, scene).

    Args:
        planners: name -> ``factory(seed)`` building the planner for one seed; a planner
            with a ``watch(policy)`` method (:class:`~policies.planners.OraclePlanner`) is
            given the traffic's scene policy.
        traffics: the traffic of the other vehicles (adversary seeded with the seed).
        scenes: the scenes.
        seeds: seeds of the adversary's noise and of the random planner.
        config: env configuration (default: the library's, 10 s episodes ending at an
            ego collision or off-road).
        progress: called after each episode with its label (planner, traffic, seed),
            e.g. a tqdm bar's update.

    Returns:
        ``{(planner name, traffic label): records}`` in (seed, scene) order.
    """
    torch.set_num_threads(1)
    results: dict[tuple[str, str], list[EpisodeRecord]] = {}
    for traffic in traffics:
        for name, factory in planners.items():
            records = results.setdefault((name, traffic.label), [])
            for seed in seeds:
                planner, others = factory(seed), make_traffic(traffic, seed)
                if callable(getattr(planner, "watch", None)):  # the oracle reads their plans
                    planner.watch(others)
                with ClosedLoop(planner, others, config) as loop:
                    for scene in scenes:
                        records.append(loop.run(scene, seed=seed))
                        if progress is not None:
                            progress(f"{name} vs {traffic.label}, seed {seed}")
    return results


def summarize_ego(records: Sequence[EpisodeRecord]) -> dict[str, dict[str, Any]]:
    """The ego's metrics with 95% intervals: ``{name: {"value", "low", "high", "n"}}``.

    * ``ego_collision_rate``, ``ego_offroad_rate``: shares of episodes (Wilson);
    * ``ego_failure_rate``: share with a collision or an off-road excursion (Wilson);
    * ``avoidable_failure_rate``: share with an ego collision the ego could have avoided
      (:mod:`policies.stress.failures`: a hindsight escape search found a witness);
    * ``progress`` [m]: distance driven by the ego (bootstrap);
    * ``ego_collisions_per_km``: episodes with an ego collision per kilometre the ego drove
      (exact Poisson interval): the rate of an ego that crawls is not lower per km;
    * ``slow_ego_share``: mean share of the ego's steps below ``MIN_ATTACK_SPEED``, where
      the adversary starts no attack (bootstrap): an ego that crawls is spared, so read
      the rates next to it and to progress;
    * ``time_to_first_ego_collision`` [s]: over the episodes with one (bootstrap).
    """
    from policies.statistics import wilson_interval

    base = summarize(list(records))
    failures = sum(r.metrics["ego_collided"] or r.metrics["ego_offroad"] for r in records)
    low, high = wilson_interval(failures, len(records))
    distances = [progress(r) for r in records]
    avoidable = sum(any(f.avoidable for f in analyse(record)) for record in records)
    d_low, d_high = mean_interval(distances)
    return {
        "ego_collision_rate": base["ego_collision_rate"],
        "ego_offroad_rate": base["ego_offroad_rate"],
        "ego_failure_rate": _entry(failures / max(len(records), 1), low, high, len(records)),
        "avoidable_failure_rate": rate(avoidable, len(records)),
        "progress": _entry(float(np.mean(distances)), d_low, d_high, len(distances)),
        "ego_collisions_per_km": per_km(
            sum(bool(r.metrics["ego_collided"]) for r in records), float(np.sum(distances))
        ),
        "slow_ego_share": mean_summary(
            [slow_ego_steps(r) / (r.states.shape[1] - 1) for r in records if r.states.shape[1] > 1]
        ),
        "time_to_first_ego_collision": base["time_to_first_ego_collision"],
    }


def _entry(value: float, low: float, high: float, count: int) -> dict[str, Any]:
    clean = [None if not np.isfinite(x) else float(x) for x in (value, low, high)]
    return dict(zip(("value", "low", "high"), clean, strict=True)) | {"n": count}
