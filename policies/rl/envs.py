"""The ego's training env: ``RiskFlowEgo-v0`` with the policy's actions and a settable adversary.

:class:`EgoInterface` is how a policy's observations and actions map to the env's, one
object for training (:class:`EgoTrainingEnv`) and evaluation
(:class:`~policies.rl.evaluation.PPOPlanner`):

* **maneuver actions** (``maneuver_actions``): the policy picks one of the 15 fixed
  maneuvers of :func:`policies.rl.features.maneuvers` (``Discrete(15)``) and follows it
  for ``action_repeat`` steps;
* otherwise **normalised actions** in ``[-1, 1]^2`` (what SB3's Gaussian policies expect),
  mapped by :func:`scale_action` so that 0 is "keep speed and heading" (0 m/s^2, 0 rad/s):
  -1 is the strongest braking (``accel_min``), +1 the strongest acceleration
  (``accel_max``), and the yaw rate is ``u * yaw_rate_max``. A plain affine map of
  ``[-8, 5]`` would put 0 at -1.5 m/s^2, so an untrained policy would brake;
* optionally **residual**: with ``base_planner`` (``"idm"`` or ``"lane"``), the policy's
  action is added to that planner's (:func:`compose_action`), so that 0 (or a straight
  maneuver) is "drive as the base planner does";
* optionally the **maneuver features** (``maneuver_features``,
  :class:`~policies.rl.features.ManeuverFeatures`) appended to the observation.

:class:`EgoTrainingEnv` adds ``action_repeat`` env steps per decision, with maneuver
actions the **action mask** in every info (``info["action_mask"]``, (M,) bool:
:meth:`EgoInterface.action_mask`), the **episode outcome** in the last step's info
(``ego_collision`` and ``ego_offroad``: 1.0 if it happened at any step of the episode,
logged by the training callbacks) and
:meth:`EgoTrainingEnv.set_adversary_stage`, which ramps the adversary (curriculum).

:func:`make_env` is the factory that ``SubprocVecEnv`` / ``DummyVecEnv`` call in each
worker: it seeds the adversary per worker and limits torch to one thread per worker.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import gymnasium
import numpy as np

from policies.dataclass_cli import check_at_least, check_choices
from policies.rl.adversary import AdversaryStage, ScenePolicyConfig, apply_stage, make_traffic
from riskflow_env.config import DynamicsConfig, EnvConfig, is_integer
from riskflow_env.scenarios import SPLITS
from riskflow_env.view import SceneView
from riskflow_env.wrappers import EgoEnv

BASE_PLANNERS = ("none", "idm", "lane")
MASK_STEPS = 10  # [steps] look-ahead of the action mask (1 s)


def make_base_planner(name: str, dynamics: DynamicsConfig):
    """The base planner of a residual policy (None for ``"none"``)."""
    if name not in BASE_PLANNERS:
        raise ValueError(f"base_planner must be one of {BASE_PLANNERS}, got {name!r}")
    if name == "none":
        return None
    from policies.planners import IDMPlanner, LaneKeepingPlanner

    return (IDMPlanner if name == "idm" else LaneKeepingPlanner)(dynamics=dynamics)


def compose_action(
    action: np.ndarray | int,
    base: np.ndarray | None,
    dynamics: DynamicsConfig,
    maneuvers: np.ndarray | None = None,
    substep: int = 0,
    normalized: bool = True,
) -> np.ndarray:
    """The env action of a policy action, plus the base planner's action ``base`` (accel
    [m/s^2], yaw rate [rad/s]) when there is one, clipped to the dynamics bounds. Used by
    training (:class:`EgoTrainingEnv`) and evaluation
    (:class:`~policies.rl.evaluation.PPOPlanner`) alike.

    Args:
        action: normalised ``(u_accel, u_yaw)`` (:func:`scale_action`), or with
            ``maneuvers`` the index of a maneuver.
        base: the base planner's action, or None.
        dynamics: the bounds.
        maneuvers: (M, H, 2) maneuver action sequences (:func:`policies.rl.features.maneuvers`)
            for a discrete policy; None for a continuous one.
        substep: env steps since the policy chose ``action`` (a maneuver is followed
            along its sequence while it is held).
        normalized: a continuous ``action`` is normalised (else it is already (accel
            [m/s^2], yaw rate [rad/s])).
    """
    if maneuvers is None and not normalized:
        own = np.asarray(action, dtype=np.float64).reshape(2)
    elif maneuvers is None:
        own = scale_action(action, dynamics)
    else:
        own = maneuvers[int(action), min(substep, maneuvers.shape[1] - 1)]
    if base is None:
        return np.asarray(own, dtype=np.float64).copy()
    low = [dynamics.accel_min, -dynamics.yaw_rate_max]
    high = [dynamics.accel_max, dynamics.yaw_rate_max]
    return np.clip(own + np.asarray(base, dtype=np.float64), low, high)


def scale_action(action: np.ndarray, dynamics: DynamicsConfig) -> np.ndarray:
    """Normalised ``(u_accel, u_yaw)`` in ``[-1, 1]`` (clipped) -> (accel [m/s^2], yaw rate
    [rad/s]); 0 maps to 0, -1 to ``accel_min``, +1 to ``accel_max`` / ``yaw_rate_max``.
    One action (any shape of 2 values) gives (2,); a batch (N, 2) gives (N, 2)."""
    u = np.asarray(action, dtype=np.float64)
    u = np.clip(u if u.ndim == 2 else u.reshape(2), -1.0, 1.0)
    gain = np.where(u[..., 0] >= 0, dynamics.accel_max, -dynamics.accel_min)
    return np.stack([u[..., 0] * gain, u[..., 1] * dynamics.yaw_rate_max], axis=-1)


def record_outcome(outcome: np.ndarray, info: Mapping[str, Any]) -> np.ndarray:
    """The episode outcome so far, ``outcome`` (2, ...) = (ego_collision, ego_offroad), each
    1.0 once it happened, updated with a step's ``info`` (``collided``,
    ``offroad_fraction``: scalars for one scene, (N,) arrays for a batch)."""
    collided = np.asarray(info["collided"], dtype=np.float64)
    offroad = (np.asarray(info["offroad_fraction"]) > 0).astype(np.float64)
    return np.maximum(outcome, np.stack([collided, offroad]))


class EgoInterface:
    """A policy's view of the ego: its observation and how its actions drive (module
    docstring). Shared by :class:`EgoTrainingEnv` and
    :class:`~policies.rl.evaluation.PPOPlanner`, so that training and evaluation see and act
    alike (evaluation adds only the action mask's filter, ``PPOPlanner(mask_actions=True)``).

    Args:
        dynamics: the env's dynamics (bounds and time step).
        base_planner: ``"none"``, ``"idm"`` or ``"lane"``.
        action_repeat: env steps per policy decision (the action is held; the base
            planner plans every step).
        maneuver_features: append the maneuver-clearance features to the observation.
        maneuver_actions: the policy's actions are maneuver indices.
        maneuver_set: ``"compact"`` (15 maneuvers) or ``"mpc"`` (the sampling MPC's 200),
            for both (:func:`policies.rl.features.maneuvers`).
        normalize_actions: continuous actions are normalised, in ``[-1, 1]^2``
            (:func:`scale_action`; what SB3's Gaussian policies expect); False: the env's
            own (accel [m/s^2], yaw rate [rad/s]) in its action space, as ``RiskFlowEgo-v0``.
    """

    def __init__(
        self,
        dynamics: DynamicsConfig,
        base_planner: str = "none",
        action_repeat: int = 1,
        maneuver_features: bool = False,
        maneuver_actions: bool = False,
        maneuver_set: str = "compact",
        normalize_actions: bool = True,
    ) -> None:
        if not (is_integer(action_repeat) and action_repeat >= 1):
            raise ValueError(f"action_repeat must be an int >= 1, got {action_repeat!r}")
        from policies.rl.features import ManeuverFeatures, maneuvers

        self.dynamics, self.action_repeat = dynamics, int(action_repeat)
        self.normalize_actions = bool(normalize_actions)
        self.base = make_base_planner(base_planner, dynamics)
        chosen = maneuvers(maneuver_set=maneuver_set)  # checks the name
        self.features = (
            ManeuverFeatures(dynamics=dynamics, maneuver_set=maneuver_set)
            if maneuver_features
            else None
        )
        self.maneuvers = chosen if maneuver_actions else None
        self._base: np.ndarray | None = None  # the base planner's last action

    def action_space(self) -> gymnasium.Space:
        """``Discrete(M)`` for maneuver actions, else ``Box([-1, 1]^2)`` (normalised) or the
        env's ``Box([accel_min, -yaw_rate_max], [accel_max, yaw_rate_max])``."""
        if self.maneuvers is not None:
            return gymnasium.spaces.Discrete(len(self.maneuvers))
        if not self.normalize_actions:
            d = self.dynamics
            low = np.array([d.accel_min, -d.yaw_rate_max], np.float32)
            return gymnasium.spaces.Box(low, np.array([d.accel_max, d.yaw_rate_max], np.float32))
        return gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def observation_space(self, env_space: gymnasium.spaces.Box) -> gymnasium.spaces.Box:
        """The policy's observation space, given the env's: its bounds, then the maneuver
        features' (each clipped to [-CAP, CAP] m, :mod:`policies.rl.features`)."""
        if self.features is None:
            return env_space
        from policies.rl.features import CAP

        size = self.features.size
        low = np.concatenate([env_space.low, np.full(size, -CAP, np.float32)])
        high = np.concatenate([env_space.high, np.full(size, CAP, np.float32)])
        return gymnasium.spaces.Box(low, high, dtype=np.float32)

    def reset(self, view: SceneView) -> None:
        """New episode (the base planner's lane graph and route)."""
        self._base = None
        if self.base is not None:
            self.base.reset(view)

    def observe(self, observation: np.ndarray, view: SceneView) -> np.ndarray:
        """The policy's observation: the env's, with the maneuver features if enabled."""
        if self.features is None:
            return observation
        return self.features.augment(observation, view)

    def action_mask(self, view: SceneView) -> np.ndarray | None:
        """(M,) bool with maneuver actions, None for continuous ones: the maneuvers that
        keep the ego's footprint on the road over the next ``MASK_STEPS`` (the largest
        footprint SDF <= 0 m; as highway-env's available actions, a lane change is
        unavailable where there is no road to change to), each predicted as it is driven:
        plus the base planner's last action, held; every maneuver when none does.

        1 s, not the features' 3 s: the base planner's steering changes along a curve, and
        holding it for 3 s puts lane keeping's own choice off the road in 8% of its
        decisions on the training bank (2 s: 3%, 1 s: 0.1%, where it never left the road)."""
        if self.maneuvers is None:
            return None
        from riskflow_env import dynamics as unicycle
        from riskflow_env.geometry import footprint_points

        actions = self.maneuvers[:, :MASK_STEPS]
        actions = actions if self._base is None else actions + self._base
        low = [self.dynamics.accel_min, -self.dynamics.yaw_rate_max]
        high = [self.dynamics.accel_max, self.dynamics.yaw_rate_max]
        ego = view.history[0, -1]
        paths = unicycle.rollout(ego[None], np.clip(actions, low, high), self.dynamics)
        footprint = footprint_points(paths[..., :2], paths[..., 3], view.length[0], view.width[0])
        mask = view.map.sdf_at(footprint).max(axis=(-1, -2)) <= 0.0
        return mask if mask.any() else np.ones_like(mask)

    def env_action(
        self, action: np.ndarray | int, observation: np.ndarray, view: SceneView, substep: int
    ) -> np.ndarray:
        """(2,) env action (accel [m/s^2], yaw rate [rad/s]) of a policy action chosen
        ``substep`` steps ago, with the base planner's action for ``view`` added."""
        base = None if self.base is None else self.base(observation, view)
        self._base = base
        return compose_action(
            action, base, self.dynamics, self.maneuvers, substep, self.normalize_actions
        )


INTERFACE_OPTIONS = tuple(inspect.signature(EgoInterface).parameters)[1:]  # after dynamics


@dataclass(frozen=True)
class EgoEnvConfig:
    """Everything a worker needs to build its env (picklable for ``SubprocVecEnv``).

    Attributes:
        env: the parallel env's configuration (episode length, rewards, termination).
        traffic: the scene policy of the other vehicles.
        split: shipped scenario bank the episodes are drawn from (``"train"``/``"eval"``).
        scenes: use only the first ``scenes`` scenes of the split (None: all).
        base_planner: ``"none"`` (the policy's action is the action) or ``"idm"`` (the
            policy's action is a residual added to the IDM planner's) or ``"lane"``
            (added to lane keeping at constant speed).
        action_repeat: env steps per policy action.
        maneuver_features: append the maneuver-clearance features to the observation.
        maneuver_actions: the policy chooses among fixed maneuvers (discrete actions).
        maneuver_set: which maneuvers, ``"compact"`` or ``"mpc"`` (:class:`EgoInterface`).
    """

    env: EnvConfig = field(default_factory=EnvConfig)
    traffic: ScenePolicyConfig = field(default_factory=ScenePolicyConfig)
    split: str = "train"
    scenes: int | None = None
    base_planner: str = "none"
    action_repeat: int = 1
    maneuver_features: bool = False
    maneuver_actions: bool = False
    maneuver_set: str = "compact"

    def __post_init__(self) -> None:
        from policies.rl.features import MANEUVER_SETS

        for name, kind in (("env", EnvConfig), ("traffic", ScenePolicyConfig)):
            value = getattr(self, name)
            if not isinstance(value, kind):
                expected = f"EgoEnvConfig.{name} must be of type {kind.__name__}"
                raise TypeError(f"{expected}, got {type(value).__name__}")
        choices = {"split": SPLITS, "base_planner": BASE_PLANNERS, "maneuver_set": MANEUVER_SETS}
        check_choices(self, choices, owner="EgoEnvConfig")
        check_at_least(self, {"scenes": 1, "action_repeat": 1}, ("scenes",), owner="EgoEnvConfig")
        for name in ("maneuver_features", "maneuver_actions"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"EgoEnvConfig.{name} must be a bool, got {getattr(self, name)!r}")


class EgoTrainingEnv(gymnasium.Wrapper):
    """The policy's actions and observation (:class:`EgoInterface`), ``action_repeat`` env
    steps per decision, episode outcome in ``info``, settable adversary (module docstring).

    Args:
        env: the ego's Gymnasium view.
        **interface: ``base_planner``, ``action_repeat``, ``maneuver_features``,
            ``maneuver_actions``, ``maneuver_set`` of :class:`EgoInterface`.
    """

    def __init__(self, env: EgoEnv, **interface: Any) -> None:
        super().__init__(env)
        self.interface = EgoInterface(env.parallel_env.config.dynamics, **interface)
        self.observation_space = self.interface.observation_space(env.observation_space)
        self.action_space = self.interface.action_space()
        self._outcome = {"ego_collision": 0.0, "ego_offroad": 0.0}
        self._observation: np.ndarray | None = None

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        self._outcome = {"ego_collision": 0.0, "ego_offroad": 0.0}
        self._observation, info = self.env.reset(**kwargs)
        view = self.env.unwrapped.parallel_env.view()
        self.interface.reset(view)
        return self.interface.observe(self._observation, view), self._with_mask(info, view)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """``action_repeat`` env steps with the same policy action (the base planner, if
        any, plans every step); the reward is their sum."""
        total = 0.0
        for substep in range(self.interface.action_repeat):
            view = self.env.unwrapped.parallel_env.view()
            action_now = self.interface.env_action(action, self._observation, view, substep)
            observation, reward, terminated, truncated, info = self.env.step(action_now)
            self._observation = observation
            self._record_outcome(info)
            total += reward
            if terminated or truncated:
                info = {**info, **self._outcome}
                break
        view = self.env.unwrapped.parallel_env.view()
        observation = self.interface.observe(observation, view)
        return observation, total, terminated, truncated, self._with_mask(info, view)

    def action_masks(self) -> np.ndarray:
        """The current action mask (:meth:`EgoInterface.action_mask`; sb3-contrib's
        ``MaskablePPO`` calls this name); an AttributeError for continuous actions."""
        mask = self.interface.action_mask(self.env.unwrapped.parallel_env.view())
        if mask is None:
            raise AttributeError("action_masks: the env has continuous actions (no mask)")
        return mask

    def _with_mask(self, info: dict[str, Any], view: SceneView) -> dict[str, Any]:
        """``info`` with ``action_mask`` (maneuver actions only)."""
        mask = self.interface.action_mask(view)
        return info if mask is None else {**info, "action_mask": mask}

    def _record_outcome(self, info: dict[str, Any]) -> None:
        so_far = np.array([self._outcome["ego_collision"], self._outcome["ego_offroad"]])
        collision, offroad = record_outcome(so_far, info).tolist()
        self._outcome = {"ego_collision": collision, "ego_offroad": offroad}

    def set_adversary_stage(self, stage: AdversaryStage) -> None:
        """Set k, guidance weight and target of the RiskFlow adversary (next cycle on)."""
        apply_stage(self.env.unwrapped.policy, stage)


def interface_options(source: Any) -> dict[str, Any]:
    """The :class:`EgoInterface` options of ``source``: its attributes (an
    :class:`EgoEnvConfig`, a script's options) or a mapping's keys (``options.json``)."""
    if isinstance(source, Mapping):
        return {name: source[name] for name in INTERFACE_OPTIONS if name in source}
    return {name: getattr(source, name) for name in INTERFACE_OPTIONS if hasattr(source, name)}


def training_scenes(config: EgoEnvConfig) -> list:
    """The scenes of ``config``: its shipped split, the first ``config.scenes`` of them."""
    from riskflow_env.scenarios import shipped_bank

    bank = shipped_bank(config.split)
    return list(bank) if config.scenes is None else [bank[i] for i in range(config.scenes)]


def build_env(config: EgoEnvConfig, seed: int = 0) -> EgoTrainingEnv:
    """One training env (not yet reset); the adversary's noise seed is ``seed``."""
    policy = make_traffic(config.traffic, seed=seed)
    env = EgoEnv(config=config.env, scenarios=training_scenes(config), policy=policy)
    return EgoTrainingEnv(env, **interface_options(config))


def make_env(config: EgoEnvConfig, rank: int, seed: int) -> Callable[[], gymnasium.Env]:
    """Factory of worker ``rank``'s env for ``SubprocVecEnv`` / ``DummyVecEnv``, wrapped in
    SB3's ``Monitor`` (episode returns and lengths). The adversary of worker ``rank`` draws
    its noise from ``seed * 1000 + rank``; the env's scene draws are seeded by the vector
    env (``VecEnv.seed``, which SB3's ``PPO(seed=...)`` calls)."""

    def thunk() -> gymnasium.Env:
        import torch
        from stable_baselines3.common.monitor import Monitor

        from policies.rl.signals import ignore_interrupts_in_worker

        ignore_interrupts_in_worker()  # Ctrl-C: the main process saves, then stops us
        torch.set_num_threads(1)  # one core per worker; the adversary plans on one thread
        return Monitor(build_env(config, seed=seed * 1000 + rank))

    return thunk
