"""Reinforcement learning of an ego against the RiskFlow adversary (the ``rl`` extra).

* :mod:`policies.rl.adversary` — the traffic (RiskFlow adversary, unguided generator, IDM)
  and the curriculum stages (k, guidance weight, target);
* :mod:`policies.rl.envs` — the ego's training env (normalised or maneuver actions, a
  base planner for residual actions, action repeat, episode outcome, settable adversary)
  and the vector-env factory;
* :mod:`policies.rl.vector_env` — ``EgoVectorEnv``: N scenes stepped as one batch, the
  adversary planning them in one call (a Gymnasium ``VectorEnv``);
  :mod:`policies.rl.sb3_vec_env` — it as an SB3 ``VecEnv``; :mod:`policies.rl.sb3_shards` —
  its scenes split over worker processes, one per core;
* :mod:`policies.rl.features` — the fixed maneuvers and their predicted clearance, as
  observation features and as discrete actions;
* :mod:`policies.rl.curriculum` — the linear curriculum and the SB3 callbacks (needs
  stable-baselines3);
* :mod:`policies.rl.evaluation` — trained / baseline ego planners in closed loop, summaries
  with 95% intervals; :mod:`policies.rl.paired` — trained vs untrained on paired
  episodes (difference, interval, McNemar test); :mod:`policies.rl.report` — Markdown
  tables and plot;
* :mod:`policies.rl.marl` — the parallel env as a SuperSuit / SB3 vector env with
  parameter sharing, and the reward of learned adversaries.

Examples: ``examples/train_ego_ppo.py``, ``examples/evaluate_ego.py``,
``examples/train_adversaries_marl.py``; results in ``docs/tutorials/rl-ego.md``.
"""

from __future__ import annotations

from policies.rl.adversary import AdversaryStage, ScenePolicyConfig, apply_stage, make_traffic
from policies.rl.envs import EgoEnvConfig, EgoTrainingEnv, build_env, make_env, scale_action
from policies.rl.vector_env import EgoVectorEnv, build_vector_env

__all__ = [
    "AdversaryStage",
    "EgoEnvConfig",
    "EgoTrainingEnv",
    "EgoVectorEnv",
    "ScenePolicyConfig",
    "apply_stage",
    "build_env",
    "build_vector_env",
    "make_env",
    "make_traffic",
    "scale_action",
]
