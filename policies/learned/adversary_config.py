"""``AdversaryConfig``: the options every learned adversary shares, as one typed object.

RiskFlow, STRIVE-style, the unguided generator and the guided-diffusion baselines plan
alike (:mod:`policies.pipeline`): the size K of the controllable set, the
planning interval, the guidance target and weights, the ranking threshold, the noise
seed, the device, the window options and the torch threads. Each takes them as one
``AdversaryConfig``, or as keywords that build one, next to its own options::

    RiskFlowAdversary(AdversaryConfig(k=5, target="ego"), guidance_steps=20)
    RiskFlowAdversary(k=5, target="ego", guidance_steps=20)  # the same policy

Beside it, the checks every adversary constructor shares: :func:`check_model_pair` (a
model comes with its normalizer) and :func:`default_window_config` (the windows a model
was trained on).
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from collections.abc import Mapping
from dataclasses import dataclass
from numbers import Real
from typing import Any

import numpy as np
import torch

from policies.cli_inputs import DT, check_device, check_interval
from policies.dataclass_cli import check_at_least, check_choices
from policies.learned.config import ModelConfig
from policies.learned.guidance_losses import TARGETS, ObjectiveConfig
from policies.learned.plan_stitching import DEFAULT_HOLD_DISTANCE
from policies.learned.ranking import DEFAULT_THRESHOLD, check_k
from policies.learned.windows import WindowConfig
from riskflow_env.config import is_number, plain_number
from riskflow_env.processes import MAX_THREADS


@dataclass(frozen=True)
class AdversaryConfig:
    """Options shared by every learned adversary.

    Attributes:
        k: size of the controllable set ``A_c``: an int >= 0 or ``"all"``; 0 gives the
            unguided generator.
        planning_interval: time between re-plans [s]; a multiple of the env's ``dt``
            between ``dt`` and the plan horizon.
        target: ``"others"`` (the paper's: toward any agent outside ``A_c``) or ``"ego"``
            (:class:`~policies.learned.guidance_losses.Target`).
        lambda_adv: weight of ``L_adv`` [1/m]; > 0 is more adversarial.
        lambda_map: weight of ``L_map`` [1/m^2], >= 0 (default: ``ObjectiveConfig``'s, 20).
        guidance_horizon: ``T_g`` [steps] of ``L_adv``, ``L_map`` and ``L_sep``; None: the
            target's default (the whole plan with ``"others"``, 3 s with ``"ego"``).
        rank_threshold: risk above which a pair is an edge of the risk graph (ranking).
        seed: noise seed (the noise of cycle ``c`` of episode ``e`` comes from
            ``(seed, e, c)``).
        device: torch device of the model.
        window_config: window options; None: the model's training windows. Its
            ``dynamics`` (dt and bounds) must be the env's.
        threads: torch CPU threads while planning (restored after); None keeps torch's
            setting. One is the default: a cycle is hundreds of tiny ops, which extra
            threads only slow down (on CPU).
        hold_distance: [m] a vehicle at rest whose new plan moves it less than this over
            the horizon keeps its brake on (:mod:`policies.learned.plan_stitching`);
            default 4 (parked cars stay parked); 0: off.
        stitch_steps: [steps] a new plan's first actions blended with the plan being
            executed (:mod:`policies.learned.plan_stitching`); None (default): 15 for a
            policy that blends first (``RiskFlowAdversary``, ``NominalGenerator``,
            STRIVE-style), 5 for one that blends after planning (the diffusion
            baselines); 0: switch at once.
    """

    k: int | str = 5
    planning_interval: float = 0.5
    target: str = "others"
    lambda_adv: float = 50.0
    lambda_map: float = ObjectiveConfig.lambda_map
    guidance_horizon: int | None = None
    rank_threshold: float = DEFAULT_THRESHOLD
    seed: int = 0
    device: torch.device | str = "cpu"
    window_config: WindowConfig | None = None
    threads: int | None = 1
    hold_distance: float = DEFAULT_HOLD_DISTANCE
    stitch_steps: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "k", check_k(self.k))
        window = self.window_config
        if window is not None and not isinstance(window, WindowConfig):
            raise TypeError(
                f"AdversaryConfig.window_config must be None or a WindowConfig, "
                f"got {type(window).__name__}"
            )
        interval = self.planning_interval
        if isinstance(interval, bool) or not isinstance(interval, Real):
            raise ValueError(
                f"AdversaryConfig.planning_interval must be a number [s], got {interval!r}"
            )
        # a multiple of the env's dt; the plan horizon is the model's, checked at reset
        dt = DT if window is None else window.dynamics.dt
        check_interval(interval, dt, None, "AdversaryConfig.planning_interval")
        owner = "AdversaryConfig"
        optional = ("guidance_horizon", "threads")
        lows = {"guidance_horizon": 1, "threads": 1}
        check_at_least(self, lows, optional, owner, highs={"threads": MAX_THREADS})
        check_choices(self, {"target": TARGETS}, owner)
        for name in ("lambda_adv", "lambda_map", "rank_threshold"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
                raise ValueError(f"AdversaryConfig.{name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, plain_number(value))  # numpy scalars as Python
        if self.lambda_map < 0:
            raise ValueError(
                f"AdversaryConfig.lambda_map must be >= 0 [1/m^2], got {self.lambda_map!r}"
            )
        hold = self.hold_distance
        if not is_number(hold) or not 0 <= hold < math.inf:  # numpy scalars too, no bools
            raise ValueError(
                f"AdversaryConfig.hold_distance must be a finite number >= 0 [m], got {hold!r}"
            )
        object.__setattr__(self, "hold_distance", float(plain_number(hold)))
        stitch = self.stitch_steps
        if stitch is not None:
            if isinstance(stitch, bool) or not isinstance(stitch, (int, np.integer)) or stitch < 0:
                raise ValueError(
                    f"AdversaryConfig.stitch_steps must be None or an int >= 0 [steps], "
                    f"got {stitch!r}"
                )
            object.__setattr__(self, "stitch_steps", int(stitch))
        seed = self.seed
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"AdversaryConfig.seed must be an int >= 0, got {seed!r}")
        object.__setattr__(self, "seed", int(seed))
        check_device(self.device, "AdversaryConfig.device")

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """The names of the shared options."""
        return tuple(field.name for field in dataclasses.fields(cls))

    @classmethod
    def resolve(
        cls, config: AdversaryConfig | None, options: Mapping[str, Any], owner: str
    ) -> AdversaryConfig:
        """``config``, or the one that ``options`` (keywords of ``owner``'s constructor,
        each a field of this class) build; TypeError for unknown keywords or both."""
        unknown = sorted(set(options) - set(cls.field_names()))
        if unknown:
            raise TypeError(
                f"{owner} got unexpected keyword argument(s) {unknown}; the shared options "
                f"are {cls.field_names()}"
            )
        if config is None:
            return cls(**options)
        if not isinstance(config, cls):
            raise TypeError(f"config must be an AdversaryConfig, got {type(config).__name__}")
        if options:
            raise TypeError(f"{owner}: pass either config or {sorted(options)}, not both")
        return config

    def objective(self) -> dict[str, Any]:
        """The guidance objective's options (``ObjectiveConfig`` fields) of this config."""
        return {
            "lambda_adv": self.lambda_adv,
            "lambda_map": self.lambda_map,
            "horizon": self.guidance_horizon,
            "target": self.target,
        }


def option_names(cls: type) -> tuple[str, ...]:
    """Keyword options of a scene policy class: its constructor's, those of the classes it
    forwards ``**options`` to, and :class:`AdversaryConfig`'s fields when a constructor
    takes a ``config`` (``riskflow-eval --set`` checks options against these)."""
    names: list[str] = []
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        parameters = inspect.signature(init).parameters
        keywords = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        for name, parameter in parameters.items():
            if name in ("self", "config") or parameter.kind not in keywords:
                continue
            if name not in names:
                names.append(name)
        if "config" in parameters:
            names += [name for name in AdversaryConfig.field_names() if name not in names]
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
            break  # this constructor takes no more than it names
    return tuple(names)


def default_window_config(config: ModelConfig) -> WindowConfig:
    """The windows a model with architecture ``config`` was trained on (history, plan
    length and map crop size; the other options at their defaults)."""
    return WindowConfig(
        history_steps=config.history_steps,
        future_steps=config.future_steps,
        crop_size=config.map_size,
    )


def check_model_pair(model: object, normalizer: object, name: str) -> None:
    """A model and its normalizer go together: both given or neither (then the shipped
    checkpoint is loaded). Raises ValueError naming ``name`` (the model argument)."""
    if model is None and normalizer is not None:
        raise ValueError(f"normalizer given without its {name}: pass both or neither")
    if model is not None and normalizer is None:
        raise ValueError(f"a {name} needs the normalizer it was trained with")


HORIZON_S = WindowConfig().future_steps * DT  # [s] the shipped generator's plans


def check_planning_interval(interval: float, option: str = "--planning-interval") -> float:
    """:func:`~policies.cli_inputs.check_interval` of an adversary's re-planning interval:
    the env's time step, the shipped generator's plan horizon (``HORIZON_S``)."""
    return check_interval(interval, DT, HORIZON_S, option)


__all__ = [
    "HORIZON_S",
    "AdversaryConfig",
    "check_model_pair",
    "check_planning_interval",
    "default_window_config",
    "option_names",
]
