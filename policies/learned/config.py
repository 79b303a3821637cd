"""``ModelConfig``: the frozen, validated architecture of the RiskFlow generator.

A checkpoint carries ``ModelConfig.to_dict()`` next to the state dict, so a model is
always rebuilt with the architecture it was trained with (``generator.py``). Sizes
default to a CPU budget: one forward pass (encoder + MeanFlow head) for 32 agents in
tens of milliseconds (``benchmarks/generator_speed.py``).

Input scales divide raw features before the first linear layer so that they are of
order one; they are part of the architecture (a checkpoint trained with one set of
scales is wrong with another) and therefore live here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from riskflow_env.config import check_field_types, is_integer

# Feature layout of the per-agent history tokens (encoder.py), in the agent's own frame.
HISTORY_FEATURES = ("x", "y", "cos_dpsi", "sin_dpsi", "speed", "valid", "length", "width")
# A field of earlier versions: the crop's centre that far ahead of the agent [m].
_REMOVED_MAP_AHEAD = "map_ahead"


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of the RiskFlow generator (scene encoder + MeanFlow head).

    Attributes:
        history_steps: history length incl. the current step (31 at 10 Hz = 3 s).
        future_steps: plan horizon in steps (52 at 10 Hz = 5.2 s).
        action_dim: action channels (accel [m/s^2], yaw rate [rad/s]).
        history_patch: history steps per encoder token (the front is zero-padded).
        plan_patch: plan steps per head token; must divide ``future_steps``.
        encoder_dim: width of the scene encoder's tokens.
        head_dim: width of the MeanFlow head's tokens.
        context_dim: width of the fused per-agent context ``C_i``.
        edge_dim: width of the pair-feature embedding ``MLP(e_ij)``.
        num_heads: attention heads (must divide ``encoder_dim`` and ``head_dim``).
        encoder_layers: (temporal, social) attention layer pairs in the encoder.
        head_layers: (temporal, social, MLP) blocks in the MeanFlow head.
        mlp_ratio: hidden width of the transformer MLPs, as a multiple of the width.
        map_channels: channels of the map crops (drivable share, SDF [m]).
        map_size: crop side [px].
        map_widths: channels of the CNN's stride-2 conv stages.
        time_frequencies: sinusoid frequencies of the time embeddings of t and r - t.
        time_scale: t and r - t are multiplied by this before the sinusoids.
        history_scale: divisors of the history features, in ``HISTORY_FEATURES`` order
            (x [m], y [m], -, -, speed [m/s], -, length [m], width [m]).
        pair_scale: divisors of ``riskflow_env.risk.FEATURE_NAMES`` (dx, dy [m], -, -,
            dvx, dvy [m/s], normalised distance, risk).
        map_scale: divisors of the map crop channels (drivable share, SDF [m]).
    """

    history_steps: int = 31
    future_steps: int = 52
    action_dim: int = 2
    history_patch: int = 4
    plan_patch: int = 4
    encoder_dim: int = 64
    head_dim: int = 96
    context_dim: int = 96
    edge_dim: int = 32
    num_heads: int = 4
    encoder_layers: int = 2
    head_layers: int = 2
    mlp_ratio: int = 2
    map_channels: int = 2
    map_size: int = 48
    map_widths: tuple[int, ...] = (16, 32, 48)
    time_frequencies: int = 32
    time_scale: float = 1000.0
    history_scale: tuple[float, ...] = (20.0, 5.0, 1.0, 1.0, 10.0, 1.0, 5.0, 2.0)
    pair_scale: tuple[float, ...] = (20.0, 10.0, 1.0, 1.0, 5.0, 5.0, 5.0, 1.0)
    map_scale: tuple[float, ...] = (1.0, 5.0)

    def __post_init__(self) -> None:
        check_field_types(self)
        ints = [f.name for f in dataclasses.fields(self) if f.type in ("int", int)]
        for name in ints:
            value = getattr(self, name)
            _require(
                is_integer(value) and value > 0,
                f"ModelConfig.{name} must be a positive int, got {value!r}",
            )
            object.__setattr__(self, name, int(value))  # a numpy int as a Python one
        _require(
            self.future_steps % self.plan_patch == 0,
            f"ModelConfig.plan_patch ({self.plan_patch}) must divide future_steps "
            f"({self.future_steps})",
        )
        for name in ("encoder_dim", "head_dim"):
            _require(
                getattr(self, name) % self.num_heads == 0,
                f"ModelConfig.{name} ({getattr(self, name)}) must be a multiple of "
                f"num_heads ({self.num_heads})",
            )
        _require(
            len(self.map_widths) > 0 and all(is_integer(w) for w in self.map_widths),
            f"ModelConfig.map_widths must be a non-empty tuple of ints, got {self.map_widths!r}",
        )
        object.__setattr__(self, "map_widths", tuple(int(w) for w in self.map_widths))
        _require(self.time_scale > 0, f"ModelConfig.time_scale must be > 0, got {self.time_scale}")
        for name, size in (
            ("map_widths", None),
            ("history_scale", len(HISTORY_FEATURES)),
            ("pair_scale", 8),
            ("map_scale", self.map_channels),
        ):
            values = getattr(self, name)
            _require(isinstance(values, tuple), f"ModelConfig.{name} must be a tuple")
            _require(
                size is None or len(values) == size,
                f"ModelConfig.{name} must have {size} entries, got {len(values)}",
            )
            _require(
                all(math.isfinite(v) and v > 0 for v in values),
                f"ModelConfig.{name} entries must be finite and > 0, got {values}",
            )

    @property
    def history_tokens(self) -> int:
        """Tokens per agent history: ``ceil(history_steps / history_patch)``."""
        return -(-self.history_steps // self.history_patch)

    @property
    def plan_tokens(self) -> int:
        """Tokens per agent plan: ``future_steps / plan_patch``."""
        return self.future_steps // self.plan_patch

    def to_dict(self) -> dict[str, Any]:
        """Plain-python (JSON / ``torch.save`` safe) dict of every field."""
        return {
            f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
            for f in dataclasses.fields(self)
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError`` naming them.

        A stored ``map_ahead`` (a crop centred ahead of the agent, an option of earlier
        versions) is accepted when it is 0, the agent-centred crop every model reads now,
        and refused otherwise: such a model was trained on crops this version cannot cut.
        """
        data = dict(data)
        ahead = data.pop(_REMOVED_MAP_AHEAD, 0)
        if ahead != 0:
            raise ValueError(
                f"ModelConfig.{_REMOVED_MAP_AHEAD} = {ahead!r}: this model was trained on map "
                "crops centred ahead of the agent, which this version no longer cuts (every "
                "crop is centred on its agent); use a version that has map_ahead, or retrain"
            )
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(
                f"ModelConfig got unknown field(s) {unknown}; known fields: {sorted(names)}"
            )
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
