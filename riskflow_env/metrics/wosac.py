"""WOSAC-style likelihood realism over N rollouts of one scene (beyond the paper).

Follows the Waymo Open Sim Agents Challenge metric design (Montali et al. 2023, "The
Waymo Open Sim Agents Challenge"), with the 2024 challenge configuration
(``challenge_2024_config.textproto`` of waymo-open-dataset): features in
:mod:`riskflow_env.metrics.wosac_features`, bins, ranges and weights in ``WOSAC_2024``.

For one scene with N rollouts (records sharing the reference):

* histogram features (``independent_timesteps``): per evaluated agent, a histogram of
  its simulated values over all N rollouts and scored steps (values clipped to
  ``[min_val, max_val]``, ``num_bins`` equal bins, ``pseudocount`` added to every bin)
  gives bin probabilities; each logged value at a scored, log-valid step scores the
  log-probability of its bin;
* Bernoulli features (collision, off-road): per agent, whether it collided / went off
  road at any scored step where the log is valid, estimated from the N rollouts (two
  bins, pseudocount 0.001) and scored on the logged indication;
* per feature, ``likelihood = exp(mean log-probability)`` over all scored (agent,
  step) pairs of the scene (over agents for the Bernoulli features), in [0, 1];
* ``metametric = sum_f w_f likelihood_f / sum_f w_f``; the bucket scores
  (``kinematic``, ``interactive``, ``map_based``) are the same weighted means within
  each bucket.

Over many scenes, the scores are averaged (:func:`wosac_aggregate`). A NaN feature
(nothing scored) makes the metametric NaN. With N = 1 the histograms are single
samples: the score is defined but coarse; WOSAC uses N = 32. Time steps share one
histogram per agent, so even the log scores below 1 when an agent's feature crosses
bins over time: log replay's score is the ceiling to compare with.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from riskflow_env.config import _require, _set_finite, _set_integer
from riskflow_env.metrics.rollout import RolloutRecord
from riskflow_env.metrics.wosac_features import WOSAC_FEATURES, wosac_features


@dataclass(frozen=True)
class FeatureConfig:
    """Likelihood estimator of one feature.

    Attributes:
        weight: metametric weight.
        min_val: histogram lower edge (feature units); values are clipped into range.
        max_val: histogram upper edge.
        num_bins: number of equal bins; 0 for a Bernoulli (bool) feature.
        pseudocount: additive smoothing per bin.
    """

    weight: float
    min_val: float = 0.0
    max_val: float = 1.0
    num_bins: int = 0
    pseudocount: float = 0.001

    def __post_init__(self) -> None:
        _set_finite(self, ("weight", "min_val", "max_val", "pseudocount"))
        _require(self.weight >= 0, f"FeatureConfig.weight must be >= 0, got {self.weight}")
        _set_integer(self, "num_bins", 0)
        _require(
            self.min_val < self.max_val,
            "FeatureConfig needs min_val < max_val, "
            f"got min_val={self.min_val}, max_val={self.max_val}",
        )
        _require(
            self.pseudocount > 0,
            f"FeatureConfig.pseudocount must be > 0 (an empty bin would score log 0), "
            f"got {self.pseudocount}",
        )

    @property
    def bernoulli(self) -> bool:
        """True for a bool feature (two bins)."""
        return self.num_bins == 0


# The WOSAC 2024 configuration (waymo-open-dataset, challenge_2024_config.textproto).
WOSAC_2024: dict[str, FeatureConfig] = {
    "linear_speed": FeatureConfig(0.05, 0.0, 25.0, 10, 0.1),  # [m/s]
    "linear_acceleration": FeatureConfig(0.05, -12.0, 12.0, 11, 0.1),  # [m/s^2]
    "angular_speed": FeatureConfig(0.05, -0.628, 0.628, 11, 0.1),  # [rad/s]
    "angular_acceleration": FeatureConfig(0.05, -3.14, 3.14, 11, 0.1),  # [rad/s^2]
    "distance_to_nearest_object": FeatureConfig(0.10, -5.0, 40.0, 10, 0.1),  # [m]
    "collision_indication": FeatureConfig(0.25),
    "time_to_collision": FeatureConfig(0.10, 0.0, 5.0, 10, 0.1),  # [s]
    "distance_to_road_edge": FeatureConfig(0.10, -20.0, 40.0, 10, 0.1),  # [m]
    "offroad_indication": FeatureConfig(0.25),
}

BUCKETS = {
    "kinematic": (
        "linear_speed",
        "linear_acceleration",
        "angular_speed",
        "angular_acceleration",
    ),
    "interactive": ("distance_to_nearest_object", "collision_indication", "time_to_collision"),
    "map_based": ("distance_to_road_edge", "offroad_indication"),
}


def _bins(values: np.ndarray, config: FeatureConfig) -> np.ndarray:
    """Bin index of each value, after clipping into ``[min_val, max_val]``."""
    width = (config.max_val - config.min_val) / config.num_bins
    index = np.floor((np.clip(values, config.min_val, config.max_val) - config.min_val) / width)
    return np.clip(index, 0, config.num_bins - 1).astype(np.int64)


def histogram_log_likelihood(
    log_values: np.ndarray,
    sim_values: np.ndarray,
    sim_valid: np.ndarray,
    config: FeatureConfig,
) -> np.ndarray:
    """Log-probability of each logged value under its agent's simulated histogram.

    Args:
        log_values: (A, T) logged feature values (any where not scored).
        sim_values: (N, A, T) simulated values of N rollouts.
        sim_valid: (N, A, T) bool, the simulated samples that enter the histograms.
        config: bins, range and pseudocount (``num_bins >= 1``).

    Returns:
        (A, T) log-probabilities (<= 0). An agent without samples gets the uniform
        ``-log(num_bins)``.
    """
    num_agents, num_bins = log_values.shape[0], config.num_bins
    agent = np.broadcast_to(np.arange(num_agents)[None, :, None], sim_values.shape)
    counts = np.zeros((num_agents, num_bins))
    sim_bins = _bins(np.where(sim_valid, sim_values, config.min_val), config)
    np.add.at(counts, (agent[sim_valid], sim_bins[sim_valid]), 1.0)
    counts += config.pseudocount
    log_prob = np.log(counts / counts.sum(axis=1, keepdims=True))  # (A, bins)
    log_bins = _bins(np.nan_to_num(log_values, nan=config.min_val), config)
    return np.take_along_axis(log_prob, log_bins, axis=1)


def bernoulli_log_likelihood(
    log_flags: np.ndarray, sim_flags: np.ndarray, pseudocount: float
) -> np.ndarray:
    """Log-probability of each logged flag under its agent's simulated frequency.

    Args:
        log_flags: (A,) bool logged indications.
        sim_flags: (N, A) bool simulated indications.
        pseudocount: additive smoothing per outcome.

    Returns:
        (A,) log-probabilities.
    """
    hits = sim_flags.sum(axis=0) + pseudocount
    misses = (~sim_flags).sum(axis=0) + pseudocount
    chosen = np.where(log_flags, hits, misses)
    return np.log(chosen / (hits + misses))


def _check_scene(records: Sequence[RolloutRecord]) -> RolloutRecord:
    if not records:
        raise ValueError("wosac_scene needs at least one rollout")
    first = records[0]
    if first.drivable_map is None:
        raise ValueError("wosac_scene needs records with a drivable_map")
    for record in records[1:]:
        same = (
            record.states.shape == first.states.shape
            and record.num_context == first.num_context
            and record.dt == first.dt
            and np.array_equal(record.reference, first.reference)
            and np.array_equal(record.reference_valid, first.reference_valid)
            and np.array_equal(record.length, first.length)
            and np.array_equal(record.width, first.width)
            and np.array_equal(record.evaluated, first.evaluated)
        )
        if not same:
            raise ValueError(
                "wosac_scene needs rollouts of one scene: same shapes, reference, sizes, "
                f"evaluated agents, dt and num_context (scene {first.scene_id!r} vs "
                f"{record.scene_id!r})"
            )
    return first


def wosac_scene(
    records: Sequence[RolloutRecord], config: Mapping[str, FeatureConfig] = WOSAC_2024
) -> dict[str, float]:
    """WOSAC-style likelihoods of one scene from its N rollouts.

    Args:
        records: N rollouts of one scene (same reference, agents and sizes).
        config: estimator per feature (default the WOSAC 2024 configuration).

    Returns:
        ``{"<feature>_likelihood": ...}`` for ``WOSAC_FEATURES``, ``"metametric"``,
        ``"<bucket>"`` for ``BUCKETS``, all in [0, 1]; and ``"num_rollouts"``.
    """
    first = _check_scene(records)
    args = (first.length, first.width, first.dt, first.drivable_map)
    log = wosac_features(first.reference, first.reference_valid, *args)
    sims = [wosac_features(r.states, r.valid, *args) for r in records]
    scored = first.scored(first.reference_valid)  # (A, T): the log's scored steps
    scored_steps = first.scored_steps[None, :] & first.evaluated[:, None]

    likelihoods = {}
    for name in WOSAC_FEATURES:
        feature = config[name]
        log_values, log_ok = log[name]
        sim_values = np.stack([sim[name][0] for sim in sims])
        sim_ok = np.stack([sim[name][1] for sim in sims]) & scored_steps[None]
        if feature.bernoulli:
            # Per agent: the flag at any scored step where the log is valid (WOSAC).
            log_flag = (log_values & log_ok & scored).any(axis=1)
            sim_flag = (sim_values & sim_ok & scored[None]).any(axis=2)
            counted = scored.any(axis=1)
            values = bernoulli_log_likelihood(log_flag, sim_flag, feature.pseudocount)[counted]
        else:
            mask = log_ok & scored
            values = histogram_log_likelihood(log_values, sim_values, sim_ok, feature)[mask]
        likelihoods[name] = float(np.exp(values.mean())) if values.size else float("nan")

    out = {f"{name}_likelihood": likelihoods[name] for name in WOSAC_FEATURES}
    out["metametric"] = _weighted(likelihoods, WOSAC_FEATURES, config)
    for bucket, names in BUCKETS.items():
        out[bucket] = _weighted(likelihoods, names, config)
    out["num_rollouts"] = float(len(records))
    return out


def _weighted(
    likelihoods: Mapping[str, float], names: Sequence[str], config: Mapping[str, FeatureConfig]
) -> float:
    total = sum(config[name].weight for name in names)
    return sum(config[name].weight * likelihoods[name] for name in names) / total


def wosac_aggregate(scenes: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Mean of per-scene :func:`wosac_scene` scores over scenes (WOSAC's aggregation)."""
    if not scenes:
        return {}
    return {key: float(np.mean([scene[key] for scene in scenes])) for key in scenes[0]}
