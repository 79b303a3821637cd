"""Baseline scene policies: log replay, IDM traffic, constant velocity, the unguided
learned generator (BITS-like nominal) and STRIVE-style latent optimisation.

The guided-diffusion baselines (CTG-, CTG++-, CCDiff-style) are in
:mod:`policies.baselines.diffusion`; docs/BASELINES.md maps each to its original.
"""

from __future__ import annotations

from policies.baselines.constant_velocity import ConstantVelocityPolicy
from policies.baselines.idm import IDMParams, IDMPolicy
from policies.baselines.nominal import NominalGenerator
from policies.baselines.replay import ReplayPolicy
from policies.baselines.strive import StriveAdversary

__all__ = [
    "ConstantVelocityPolicy",
    "IDMParams",
    "IDMPolicy",
    "NominalGenerator",
    "ReplayPolicy",
    "StriveAdversary",
]
