"""Baseline scene policies: log replay, IDM traffic, constant velocity."""

from __future__ import annotations

from policies.baselines.idm import IDMParams, IDMPolicy

__all__ = ["IDMParams", "IDMPolicy"]
