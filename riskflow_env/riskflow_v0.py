"""PettingZoo-style environment module: ``from riskflow_env import riskflow_v0``, then
``riskflow_v0.parallel_env(max_cycles=100)`` or ``riskflow_v0.env()`` (the AEC view), as
PettingZoo's own environments (``pistonball_v6``) are imported; the ``_v0`` suffix is the
env's version."""

from __future__ import annotations

from riskflow_env import env, parallel_env

__all__ = ["env", "parallel_env"]
