"""Adversary curriculum: how k, guidance strength and target ramp over training.

:class:`LinearCurriculum` interpolates from ``start`` to ``end`` over the first
``ramp_fraction`` of training (``k`` rounded to the nearest int, ``lambda_adv`` linear;
``target`` switches to ``end.target`` half-way through the ramp), then holds ``end``.
:class:`CurriculumCallback` applies it to every env of a vector env before each rollout
(``VecEnv.env_method("set_adversary_stage", stage)``, through SubprocVecEnv's pipes) and
logs the stage (``curriculum/k``, ``curriculum/lambda_adv``, ``curriculum/target_ego``).
"""

from __future__ import annotations

from dataclasses import dataclass

from stable_baselines3.common.callbacks import BaseCallback

from policies.rl.adversary import AdversaryStage


@dataclass(frozen=True)
class LinearCurriculum:
    """Linear ramp of the adversary (module docstring).

    Attributes:
        start: the stage at the start of training.
        end: the stage from ``ramp_fraction`` of training on.
        ramp_fraction: share of the training steps the ramp takes, in [0, 1]
            (0: ``end`` from the start, no curriculum).
    """

    start: AdversaryStage
    end: AdversaryStage
    ramp_fraction: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.ramp_fraction <= 1.0:
            raise ValueError(
                f"LinearCurriculum.ramp_fraction must be in [0, 1], got {self.ramp_fraction}"
            )

    def stage_at(self, progress: float) -> AdversaryStage:
        """The stage after ``progress`` (share of training done, in [0, 1])."""
        if self.ramp_fraction == 0.0 or progress >= self.ramp_fraction:
            return self.end
        share = max(progress, 0.0) / self.ramp_fraction
        start, end = self.start, self.end
        if start.k == "all" or end.k == "all":
            k = end.k if share >= 0.5 else start.k
        else:
            k = round(start.k + share * (end.k - start.k))
        return AdversaryStage(
            k=k,
            lambda_adv=start.lambda_adv + share * (end.lambda_adv - start.lambda_adv),
            target=end.target if share >= 0.5 else start.target,
        )


class CurriculumCallback(BaseCallback):
    """Sets ``curriculum.stage_at(num_timesteps / total_timesteps)`` on every env before
    each rollout.

    Args:
        curriculum: the schedule.
        total_timesteps: the training budget the progress is measured against.
    """

    def __init__(self, curriculum: LinearCurriculum, total_timesteps: int) -> None:
        super().__init__()
        self.curriculum, self.total_timesteps = curriculum, max(int(total_timesteps), 1)
        self.stage: AdversaryStage | None = None

    def _on_rollout_start(self) -> None:
        stage = self.curriculum.stage_at(self.num_timesteps / self.total_timesteps)
        if stage != self.stage:
            self.training_env.env_method("set_adversary_stage", stage)
            self.stage = stage
        self.logger.record("curriculum/k", -1 if stage.k == "all" else stage.k)
        self.logger.record("curriculum/lambda_adv", stage.lambda_adv)
        self.logger.record("curriculum/target_ego", float(stage.target == "ego"))

    def _on_step(self) -> bool:
        return True


class OutcomeCallback(BaseCallback):
    """Logs the share of finished episodes in which the ego collided / left the road
    (``rollout/ego_collision_rate``, ``rollout/ego_offroad_rate``), from the
    ``ego_collision`` / ``ego_offroad`` flags of :class:`~policies.rl.envs.EgoTrainingEnv`."""

    def __init__(self) -> None:
        super().__init__()
        self._collisions: list[float] = []
        self._offroad: list[float] = []

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
            if done and "ego_collision" in info:
                self._collisions.append(info["ego_collision"])
                self._offroad.append(info["ego_offroad"])
        return True

    def _on_rollout_end(self) -> None:
        if self._collisions:
            count = len(self._collisions)
            self.logger.record("rollout/ego_collision_rate", sum(self._collisions) / count)
            self.logger.record("rollout/ego_offroad_rate", sum(self._offroad) / count)
            self.logger.record("rollout/episodes", count)
        self._collisions, self._offroad = [], []
