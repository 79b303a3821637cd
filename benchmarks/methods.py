"""Scene policies of the benchmarks, by method name (a helper, not a benchmark).

Every benchmark builds its policies with :func:`policies.registry.build_policy`, as
``riskflow-eval`` and the examples do, so that it measures what ships: a method without
options is the library's default (``riskflow`` and ``bits`` plan on the realistic base:
avoidance steps, holding at rest, blending first). The raw generator, without that rule
layer, is the method's ``-raw`` variant (``riskflow-raw``, ``bits-raw``), which a
benchmark measures next to the default when asked (``--raw``). A script of this folder
imports it as ``from methods import make_policy``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from policies.learned.adversary_config import AdversaryConfig
from policies.registry import METHODS, build_policy
from riskflow_env.view import ScenePolicy

RAW_SUFFIX = "-raw"


def raw_variant(method: str) -> str:
    """The raw-generator variant of ``method`` (``riskflow`` -> ``riskflow-raw``);
    ValueError naming the methods that have one otherwise."""
    name = method + RAW_SUFFIX
    if name not in METHODS:
        known = [m for m in METHODS if m + RAW_SUFFIX in METHODS]
        raise ValueError(f"method {method!r} has no raw variant; methods with one: {known}")
    return name


def with_raw(methods: Sequence[str], raw: bool) -> tuple[str, ...]:
    """``methods``, each followed by its raw variant when ``raw``."""
    names: list[str] = []
    for method in methods:
        names += [method, raw_variant(method)] if raw else [method]
    return tuple(names)


def make_policy(
    method: str,
    options: Mapping[str, Any] | None = None,
    *,
    k: int | str | None = None,
    planning_interval: float | None = None,
    target: str | None = None,
    seed: int | None = None,
    device: str = "cpu",
) -> ScenePolicy:
    """The scene policy of ``method`` with ``options`` (keyword arguments of its class:
    models, threads, ``--set`` values); a shared argument left None takes the library's
    default (:class:`~policies.learned.adversary_config.AdversaryConfig`)."""
    defaults = AdversaryConfig
    return build_policy(
        method,
        dict(options or {}),
        k=defaults.k if k is None else k,
        planning_interval=defaults.planning_interval
        if planning_interval is None
        else planning_interval,
        target=defaults.target if target is None else target,
        seed=defaults.seed if seed is None else seed,
        device=device,
    )
