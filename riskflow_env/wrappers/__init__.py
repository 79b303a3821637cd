"""Wrappers of the ``riskflow_v0`` env: event log, video recording, Gymnasium ego view,
fixed roster for multi-agent training libraries (RLlib, TorchRL, SuperSuit)."""

from __future__ import annotations

from riskflow_env.wrappers.ego_env import EgoEnv
from riskflow_env.wrappers.event_log import EventLogWrapper, EventRecorder
from riskflow_env.wrappers.event_log_file import read_event_log
from riskflow_env.wrappers.fixed_roster import FixedRosterEnv
from riskflow_env.wrappers.vector import sb3_vec_env
from riskflow_env.wrappers.video import VideoRecorder

__all__ = [
    "EgoEnv",
    "EventLogWrapper",
    "EventRecorder",
    "FixedRosterEnv",
    "VideoRecorder",
    "read_event_log",
    "sb3_vec_env",
]
