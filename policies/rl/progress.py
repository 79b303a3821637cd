"""A tqdm bar over a stable-baselines3 run: environment steps done, total and ETA.

SB3's own ``learn(progress_bar=True)`` needs ``rich``, which is not a dependency; this
callback needs tqdm only::

    model.learn(total, callback=[..., StepProgressBar(total, "PPO")])
"""

from __future__ import annotations

from stable_baselines3.common.callbacks import BaseCallback
from tqdm import tqdm


class StepProgressBar(BaseCallback):
    """Counts ``model.num_timesteps`` (steps of all envs together) against ``total``.

    Args:
        total: the ``total_timesteps`` given to ``learn`` (the bar shows the whole rollouts
            that reach it: what ``learn`` runs).
        desc: the bar's label.
    """

    def __init__(self, total: int, desc: str = "training") -> None:
        super().__init__()
        self.total, self.desc = total, desc
        self.bar: tqdm | None = None

    def _on_training_start(self) -> None:
        # learn() collects whole rollouts (n_steps per env) until it reaches total, so an
        # on-policy run ends at the first whole rollout past it
        start, rollout = self.num_timesteps, getattr(self.model, "n_steps", 1) * self.model.n_envs
        end = start + -(-max(self.total - start, 0) // rollout) * rollout
        self.bar = tqdm(total=end, desc=self.desc, unit="step", initial=start)

    def _on_step(self) -> bool:
        self.bar.update(self.num_timesteps - self.bar.n)
        return True

    def _on_training_end(self) -> None:
        self.bar.close()
