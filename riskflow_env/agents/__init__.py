"""The env's own scene policies: rule-based traffic and log replay (as Waymax's agents).

* :class:`IDMPolicy`: reactive IDM car following, yielding and lane keeping on the
  map's lane graph; the default traffic of the ego view (``RiskFlowEgo-v0``);
* :class:`ReplayPolicy`: tracks each vehicle's logged reference future;
* :class:`ConstantVelocityPolicy`: zero actions (keeps speed and heading).

Each implements :class:`~riskflow_env.view.ScenePolicy`; the learned adversaries live
in the ``policies`` package, which builds on this one (never the other way round).
"""

from __future__ import annotations

from riskflow_env.agents.base import CONTROLLED_GROUPS, actions_dict, controlled_mask
from riskflow_env.agents.constant_velocity import ConstantVelocityPolicy
from riskflow_env.agents.idm import IDMParams, IDMPolicy
from riskflow_env.agents.replay import ReplayPolicy

__all__ = [
    "CONTROLLED_GROUPS",
    "ConstantVelocityPolicy",
    "IDMParams",
    "IDMPolicy",
    "ReplayPolicy",
    "actions_dict",
    "controlled_mask",
]
