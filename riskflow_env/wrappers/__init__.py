"""Wrappers of the ``riskflow_v0`` env: event log, video recording."""

from __future__ import annotations

from riskflow_env.wrappers.event_log import EventLogWrapper, EventRecorder, read_event_log
from riskflow_env.wrappers.video import VideoRecorder

__all__ = ["EventLogWrapper", "EventRecorder", "VideoRecorder", "read_event_log"]
