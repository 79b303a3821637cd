"""Wrappers of the ``riskflow_v0`` env: event log, video recording, Gymnasium ego view."""

from __future__ import annotations

from riskflow_env.wrappers.ego_env import EgoEnv
from riskflow_env.wrappers.event_log import EventLogWrapper, EventRecorder, read_event_log
from riskflow_env.wrappers.video import VideoRecorder

__all__ = ["EgoEnv", "EventLogWrapper", "EventRecorder", "VideoRecorder", "read_event_log"]
