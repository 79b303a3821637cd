"""Scenarios and where they come from."""

from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.sources import ScenarioBank, ScenarioSource, as_source
from riskflow_env.scenarios.traffic import HighwayTrafficSource, TrafficConfig, place_traffic

__all__ = [
    "HighwayTrafficSource",
    "Scenario",
    "ScenarioBank",
    "ScenarioSource",
    "TrafficConfig",
    "as_source",
    "place_traffic",
]
