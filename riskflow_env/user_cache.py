"""The user cache folder of riskflow-env: files derived from data, rebuilt when deleted.

``platformdirs.user_cache_dir("riskflow-env")`` (``~/.cache/riskflow-env`` on Linux);
the environment variable ``RISKFLOW_CACHE_DIR`` overrides it. Converted ScenarioNet
maps (:mod:`riskflow_env.scenarios.map_cache`, under ``maps/``) and the window caches and
action statistics of read-only scene folders (``policies.learned.data_cache``, under
``data/``) live there. Deleting the folder is always safe.
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "RISKFLOW_CACHE_DIR"


def user_cache() -> Path:
    """The user cache folder of riskflow-env (``$RISKFLOW_CACHE_DIR`` when set)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    from platformdirs import user_cache_dir  # only needed when no folder is given

    return Path(user_cache_dir("riskflow-env"))
