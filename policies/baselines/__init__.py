"""Baseline scene policies: log replay, IDM traffic, constant velocity."""

from __future__ import annotations

from policies.baselines.constant_velocity import ConstantVelocityPolicy
from policies.baselines.idm import IDMParams, IDMPolicy
from policies.baselines.replay import ReplayPolicy

__all__ = ["ConstantVelocityPolicy", "IDMParams", "IDMPolicy", "ReplayPolicy"]
