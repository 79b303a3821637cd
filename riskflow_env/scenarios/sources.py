"""Scenario sources: where ``env.reset`` gets its next scene from."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from riskflow_env.scenarios.scenario import Scenario


@runtime_checkable
class ScenarioSource(Protocol):
    """Anything that draws scenarios from a seeded generator."""

    def sample(self, rng: np.random.Generator, max_agents: int | None = None) -> Scenario:
        """The next scenario; must depend on nothing but ``rng``'s state."""
        ...


class ScenarioBank:
    """A fixed list of scenarios, drawn uniformly at random.

    Args:
        scenarios: the scenes (at least one).
    """

    def __init__(self, scenarios: Sequence[Scenario]) -> None:
        scenarios = tuple(scenarios)
        if not scenarios:
            raise ValueError("ScenarioBank needs at least one scenario, got an empty sequence")
        for index, scenario in enumerate(scenarios):
            if not isinstance(scenario, Scenario):
                raise TypeError(
                    f"ScenarioBank: scenarios[{index}] must be a Scenario, "
                    f"got {type(scenario).__name__}"
                )
        self.scenarios = scenarios

    def __len__(self) -> int:
        return len(self.scenarios)

    @property
    def names(self) -> tuple[str, ...]:
        """The scenes' names, in order."""
        return tuple(scenario.name for scenario in self.scenarios)

    def __getitem__(self, index: int) -> Scenario:
        return self.scenarios[index]

    def sample(self, rng: np.random.Generator, max_agents: int | None = None) -> Scenario:
        """A uniformly drawn scenario (``max_agents`` is applied by the env at reset)."""
        return self.scenarios[int(rng.integers(len(self.scenarios)))]


def as_source(scenarios: ScenarioSource | Sequence[Scenario] | Scenario) -> ScenarioSource:
    """Wrap a scenario or a sequence of them as a :class:`ScenarioBank`; pass sources through."""
    if isinstance(scenarios, Scenario):
        return ScenarioBank([scenarios])
    if isinstance(scenarios, ScenarioSource):
        return scenarios
    if isinstance(scenarios, Sequence):
        return ScenarioBank(scenarios)
    raise TypeError(
        "scenarios must be a Scenario, a sequence of Scenarios or a ScenarioSource "
        f"(an object with sample(rng, max_agents)), got {type(scenarios).__name__}"
    )
