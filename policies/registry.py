"""The scene-policy registry: name -> how to build that policy (``riskflow-eval``
compares these methods; the RL recipes and the examples build their traffic here too).

Every method is a :class:`MethodSpec`: a loader that imports its policy class (lazily,
so a method whose module is missing fails only when it is asked for, naming the
module), the fixed keyword arguments that make the variant (``riskflow-noadv`` is
RiskFlow with ``lambda_adv=0``), and which of the shared arguments the class takes
(``k``, ``planning_interval``, ``target``, ``seed``, ``device``). Method options
(``--set key=value``) are further keyword arguments of the class, checked against
:func:`~policies.learned.adversary_config.option_names`; :func:`build_policy` makes one
policy for one rollout.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from policies.cli_inputs import did_you_mean
from policies.learned.adversary_config import option_names
from riskflow_env.view import ScenePolicy

SHARED = ("k", "planning_interval", "target", "seed", "device")
DIFFUSION_STEPS_OPTION = "sampling_steps"  # the DiffusionAdversary argument --diffusion-steps sets


# Options that riskflow-eval sets with flags of its own, for every method of a run.
RUN_FLAGS = {
    "k": "--k", "target": "--target", "planning_interval": "--interval", "seed": "--seeds",
    "device": "--device",
}  # fmt: skip

def _class_loader(module: str, name: str) -> Callable[[], type]:
    """A loader that imports ``module`` when called and returns its class ``name`` (an
    ImportError naming the module when it or the class is missing)."""

    def load() -> type:
        loaded = importlib.import_module(module)
        try:
            return getattr(loaded, name)
        except AttributeError as err:
            raise ImportError(f"cannot import name {name!r} from {module!r}") from err

    return load


_riskflow = _class_loader("policies.riskflow", "RiskFlowAdversary")
_diffusion = _class_loader("policies.baselines.diffusion", "DiffusionAdversary")
_strive = _class_loader("policies.baselines.strive", "StriveAdversary")
_nominal = _class_loader("policies.baselines.nominal", "NominalGenerator")
_idm = _class_loader("riskflow_env.agents", "IDMPolicy")
_replay = _class_loader("riskflow_env.agents", "ReplayPolicy")
_constant_velocity = _class_loader("riskflow_env.agents", "ConstantVelocityPolicy")


@dataclass(frozen=True)
class MethodSpec:
    """How to build one method's scene policy.

    Attributes:
        name: the method's name on the command line.
        description: one line for ``--list``.
        loader: returns the policy class (imports it).
        fixed: keyword arguments that define the variant (``--set`` cannot change them).
        takes: which of :data:`SHARED` the class takes; the others are not passed, and a
            method without ``k`` (or ``planning_interval``) is run once for all K (or
            intervals) and appears in every table.
        diffusion: takes ``--diffusion-steps`` (as ``sampling_steps``).
        reference: a reference traffic model (IDM traffic, log replay, constant
            velocity), not a scenario generator: the report shows its metrics but leaves it
            out of the CS / RS normalisation, which compares the generators.
    """

    name: str
    description: str
    loader: Callable[[], type]
    fixed: Mapping[str, Any] = field(default_factory=dict)
    takes: tuple[str, ...] = SHARED
    diffusion: bool = False
    reference: bool = False

    @property
    def uses_k(self) -> bool:
        """The method has a controllable-set size K."""
        return "k" in self.takes

    @property
    def uses_interval(self) -> bool:
        """The method re-plans every planning interval."""
        return "planning_interval" in self.takes

    def policy_class(self) -> type:
        """The policy class; ValueError naming the method when its module is missing."""
        try:
            return self.loader()
        except ImportError as err:
            raise ValueError(f"method {self.name!r} is not available: {err}") from err

    def option_names(self) -> tuple[str, ...]:
        """Keyword arguments ``--set`` may give (the class's, minus shared and fixed ones)."""
        names = option_names(self.policy_class())
        return tuple(name for name in names if name not in SHARED and name not in self.fixed)


_ADVERSARY = "adversarial guidance on the top-K agents"
# the raw generator's plans: the realistic base's rule layer (avoidance steps, holding at
# rest) left out, so its effect can be reported next to the model's own
RAW: Mapping[str, Any] = {"avoid_steps": 0, "hold_distance": 0.0}
METHODS: dict[str, MethodSpec] = {
    spec.name: spec
    for spec in (
        MethodSpec(
            "riskflow",
            f"RiskFlow: MeanFlow generator on the realistic base (bits), {_ADVERSARY}",
            _riskflow,
        ),
        MethodSpec(
            "riskflow-raw",
            "RiskFlow on the raw generator (bits-raw): no avoidance steps, no holding at rest",
            _riskflow,
            RAW,
        ),
        MethodSpec(
            "riskflow-noadv",
            "RiskFlow without L_adv (lambda_adv = 0; ablation)",
            _riskflow,
            fixed={"lambda_adv": 0.0},
        ),
        MethodSpec(
            "riskflow-nomap",
            "RiskFlow without L_map (lambda_map = 0; ablation)",
            _riskflow,
            fixed={"lambda_map": 0.0},
        ),
        MethodSpec(
            "riskflow-nosep",
            "RiskFlow without L_sep (lambda_sep = 0, the paper's objective; ablation)",
            _riskflow,
            fixed={"lambda_sep": 0.0},
        ),
        MethodSpec(
            "riskflow-diffusion",
            "RiskFlow guidance on the diffusion generator (DDIM; ablation)",
            _riskflow,
            fixed={"generator": "diffusion"},
            diffusion=True,
        ),
        MethodSpec(
            "ctg",
            f"CTG-style guided DDPM, {_ADVERSARY}",
            _diffusion,
            {"variant": "ctg"},
            diffusion=True,
        ),
        MethodSpec(
            "ctgpp",
            "CTG++-style: guidance through the predicted clean sample",
            _diffusion,
            {"variant": "ctgpp"},
            diffusion=True,
        ),
        MethodSpec(
            "ccdiff",
            "CCDiff-style: TTC causal ranking, CTG guidance on it",
            _diffusion,
            {"variant": "ccdiff"},
            diffusion=True,
        ),
        MethodSpec("strive", f"STRIVE-style latent optimisation, {_ADVERSARY}", _strive),
        MethodSpec(
            "bits",
            "BITS-like nominal: the unguided generator on the realistic base (avoidance "
            "steps, holding at rest, blending first)",
            _nominal,
            takes=("planning_interval", "seed", "device"),
        ),
        MethodSpec(
            "bits-raw",
            "the raw unguided generator: no avoidance steps, no holding at rest",
            _nominal,
            RAW,
            takes=("planning_interval", "seed", "device"),
        ),
        MethodSpec(
            "bits-diffusion",
            "the unguided diffusion generator (DDIM)",
            _nominal,
            {"generator": "diffusion"},
            takes=("planning_interval", "seed", "device"),
            diffusion=True,
        ),
        MethodSpec("idm", "IDM traffic (reactive, rule based)", _idm, takes=(), reference=True),
        MethodSpec(
            "replay", "log replay (tracking the reference)", _replay, takes=(), reference=True
        ),
        MethodSpec(
            "cv", "constant velocity (zero actions)", _constant_velocity, takes=(), reference=True
        ),
    )
}


def method_spec(name: str) -> MethodSpec:
    """The spec of ``name``; ValueError listing the known methods otherwise."""
    if name not in METHODS:
        raise ValueError(
            f"--methods: unknown method {name!r}{did_you_mean(name, METHODS)}; known: "
            f"{', '.join(METHODS)}"
        )
    return METHODS[name]


def method_list() -> str:
    """The ``--list`` text: one line per method."""
    width = max(len(name) for name in METHODS)
    return "\n".join(f"{name:<{width}}  {spec.description}" for name, spec in METHODS.items())


def parse_value(text: str) -> Any:
    """A ``--set`` value: none/null, true/false, int, float, else the string."""
    lowered = text.strip().lower()
    if lowered in ("none", "null"):
        return None
    if lowered in ("true", "false"):
        return lowered == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def method_options(
    methods: tuple[str, ...], settings: tuple[str, ...], diffusion_steps: int | None
) -> dict[str, dict[str, Any]]:
    """Per method, the options given on the command line (part of each row's key).

    Args:
        methods: method names.
        settings: ``--set`` items ``key=value`` (every method that takes ``key``; at
            least one must) or ``method.key=value`` (that method, which must take it;
            ignored when the method is not in ``methods``, so one sweep's settings
            can serve runs of a subset of its methods).
        diffusion_steps: ``--diffusion-steps`` for the diffusion methods (None: DDPM).
    """
    options: dict[str, dict[str, Any]] = {name: {} for name in methods}
    for name in methods:
        if method_spec(name).diffusion and diffusion_steps is not None:
            options[name][DIFFUSION_STEPS_OPTION] = int(diffusion_steps)
    for item in settings:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set: expected key=value or method.key=value, got {item!r}")
        scope, dot, key = key.rpartition(".")
        if dot and scope not in METHODS:
            raise ValueError(
                f"--set {item!r}: unknown method {scope!r}{did_you_mean(scope, METHODS)}"
            )
        # a method.key item for a method not in --methods is checked, then unused
        targets = [scope] if dot else [m for m in methods if key in METHODS[m].option_names()]
        if key in RUN_FLAGS:  # the run's own flags, shared by every method
            raise ValueError(f"--set {item!r}: {key} is set by {RUN_FLAGS[key]}, for every method")
        if not targets or key not in METHODS[targets[0]].option_names():
            where = scope if dot else "any of --methods"
            names = sorted(
                METHODS[scope].option_names() if dot else
                {option for m in methods for option in METHODS[m].option_names()}
            )  # fmt: skip
            raise ValueError(
                f"--set {item!r}: {key!r} is not an option of {where}"
                f"{did_you_mean(key, names)}; {'its' if dot else 'their'} options: "
                f"{', '.join(names)}"
            )
        for name in targets:
            if name in options:
                options[name][key] = parse_value(value)
    return options


def build_policy(
    name: str,
    options: Mapping[str, Any],
    *,
    k: int | str | None,
    planning_interval: float | None,
    target: str,
    seed: int,
    device: str = "cpu",
) -> ScenePolicy:
    """One scene policy of method ``name`` (the shared arguments it does not take are
    dropped; ``options`` are passed as keyword arguments)."""
    spec = method_spec(name)
    shared = dict(k=k, planning_interval=planning_interval, target=target, seed=seed, device=device)
    kwargs = {key: shared[key] for key in spec.takes} | dict(spec.fixed) | dict(options)
    return spec.policy_class()(**kwargs)
