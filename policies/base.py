"""The scene-policy contract, re-exported where policies are written.

:class:`ScenePolicy` lives beside :class:`~riskflow_env.view.SceneView` in
:mod:`riskflow_env.view`, and the helpers every policy uses (:func:`controlled_mask`,
:func:`actions_dict`) in :mod:`riskflow_env.agents.base`: the env drives its traffic
through them without importing ``policies`` (docs/explanation/architecture.md).
"""

from __future__ import annotations

from riskflow_env.agents.base import CONTROLLED_GROUPS, actions_dict, controlled_mask
from riskflow_env.view import ScenePolicy

__all__ = ["CONTROLLED_GROUPS", "ScenePolicy", "actions_dict", "controlled_mask"]
