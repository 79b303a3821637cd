"""Scene policies that drive the non-ego vehicles (docs/explanation/architecture.md).

The scene policies are importable from here, loaded on first use (``import policies``
stays light):

* ``RiskFlowAdversary``: MeanFlow generator, TTC ranking, output-space guidance;
* ``StriveAdversary``: STRIVE-style, optimises the generator's noise of ``A_c``;
* ``NominalGenerator``: the unguided learned generator (BITS-like nominal traffic);
* ``DiffusionAdversary``: CTG-, CTG++- and CCDiff-style guided diffusion;
* ``IDMPolicy``, ``ReplayPolicy``, ``ConstantVelocityPolicy``: rule-based and log replay,
  from :mod:`riskflow_env.agents` (the env's own traffic).
"""

from __future__ import annotations

from importlib import import_module

_EXPORTS = {
    "RiskFlowAdversary": "policies.riskflow.policy",
    "StriveAdversary": "policies.baselines.strive",
    "NominalGenerator": "policies.baselines.nominal",
    "DiffusionAdversary": "policies.baselines.diffusion.policy",
    "IDMPolicy": "riskflow_env.agents.idm",
    "ReplayPolicy": "riskflow_env.agents.replay",
    "ConstantVelocityPolicy": "riskflow_env.agents.constant_velocity",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> object:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'policies' has no attribute {name!r}")
    return getattr(import_module(_EXPORTS[name]), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
