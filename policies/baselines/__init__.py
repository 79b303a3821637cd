"""Baseline scene policies: the unguided learned generator (BITS-like nominal) and
STRIVE-style latent optimisation.

The guided-diffusion baselines (CTG-, CTG++-, CCDiff-style) are in
:mod:`policies.baselines.diffusion`; the rule-based references (IDM traffic, log replay,
constant velocity) ship with the env in :mod:`riskflow_env.agents`. docs/how-to/baselines.md
maps each baseline to its original.
"""

from __future__ import annotations

from policies.baselines.nominal import NominalGenerator
from policies.baselines.strive import StriveAdversary

__all__ = ["NominalGenerator", "StriveAdversary"]
