"""The base-plan generator of the one-step adversaries: MeanFlow, or diffusion seen as one step.

``RiskFlowAdversary``, the unguided generator and STRIVE-style need one thing from their
generator: ``u0 = average_velocity(eps, 0, 1; C)``, the residual whose
``eps + u0`` is every agent's normalised plan. Two kinds provide it:

* ``"meanflow"``: :class:`~policies.learned.generator.RiskFlowGenerator`, one forward
  pass (``policies/checkpoints/riskflow_default.pt``);
* ``"diffusion"``: the DDPM denoiser of the diffusion baselines
  (``policies/checkpoints/diffusion_default.pt``) wrapped in
  :class:`~policies.baselines.diffusion.sampling.OneCallSampler`: a deterministic
  ``sampling_steps``-level DDIM chain from ``eps`` (``eta = 0``), so ``eps`` still fixes
  the plan and output-space guidance applies unchanged (the ablation "MeanFlow vs the
  diffusion generator" of issue 7).

The kind of a checkpoint file is read from its ``train_config["generator"]``
(``riskflow-train --generator``; files without it are MeanFlow).
"""

from __future__ import annotations

import os

import torch

from policies.learned.checkpoint import checkpoint_kind, load_checkpoint
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from riskflow_env.config import is_integer, is_number

GENERATOR_KINDS = ("meanflow", "diffusion")
DEFAULT_SAMPLING_STEPS = 10  # DDIM levels of a diffusion base generator (its validation's)


def generator_kind(model: object) -> str:
    """The kind of a model object: a ``OneCallSampler`` is ``"diffusion"``, else MeanFlow."""
    from policies.baselines.diffusion.sampling import OneCallSampler

    return "diffusion" if isinstance(model, OneCallSampler) else "meanflow"


def load_base_generator(
    kind: str | None = None,
    checkpoint: str | os.PathLike | None = None,
    device: torch.device | str = "cpu",
    sampling_steps: int | None = None,
) -> tuple[RiskFlowGenerator, ActionNormalizer, str]:
    """Load a base-plan generator: ``(model, normalizer, kind)``.

    Args:
        kind: ``"meanflow"`` or ``"diffusion"``; None: the checkpoint's kind (MeanFlow
            without a checkpoint). With both, they must agree.
        checkpoint: a ``riskflow-train`` checkpoint file; None: the shipped one of ``kind``.
        device: where the model goes (eval mode, no gradients).
        sampling_steps: DDIM levels of a diffusion generator (None: 10); an error for
            MeanFlow (it has one step).

    Returns:
        The model (a ``RiskFlowGenerator`` or a ``OneCallSampler``, both with ``encode``,
        ``average_velocity`` and ``config``), its action normalizer and its kind.

    Raises:
        ValueError: an unknown kind, a kind the checkpoint is not, or ``sampling_steps``
            with MeanFlow.
        FileNotFoundError, CheckpointError: as ``load_generator`` / ``load_diffusion``.
    """
    if kind is not None and kind not in GENERATOR_KINDS:
        raise ValueError(f"generator must be one of {GENERATOR_KINDS} or a model, got {kind!r}")
    if checkpoint is not None:
        found = checkpoint_kind(load_checkpoint(checkpoint))
        if kind is not None and kind != found:
            raise ValueError(f"generator={kind!r}, but checkpoint {checkpoint} is a {found} model")
        kind = found
    kind = kind or "meanflow"
    if kind == "meanflow":
        if sampling_steps is not None:
            raise ValueError("sampling_steps applies to a diffusion generator only")
        from policies.learned.checkpoint import load_generator

        model, normalizer, _ = load_generator(checkpoint, device=device)
        return model, normalizer, kind
    from policies.baselines.diffusion.model import load_diffusion
    from policies.baselines.diffusion.sampling import OneCallSampler

    denoiser, normalizer, _ = load_diffusion(checkpoint, device=device)
    steps = DEFAULT_SAMPLING_STEPS if sampling_steps is None else sampling_steps
    return OneCallSampler(denoiser, steps), normalizer, kind


def resolve_generator(
    generator: object,
    normalizer: object,
    checkpoint: str | os.PathLike | None,
    sampling_steps: int | None,
    device: torch.device,
) -> tuple[object, object, str]:
    """The base generator a policy's arguments ask for, on ``device`` in eval mode, with
    its normalizer and kind: a model object with its ``normalizer``, or ``generator`` None
    or a kind name to load from ``checkpoint`` (default: the shipped file of that kind).

    Raises:
        ValueError: a model without its normalizer (or the reverse), or ``checkpoint`` /
            ``sampling_steps`` given with a model object.
    """
    from policies.learned.adversary_config import check_model_pair

    if generator is None or isinstance(generator, str):
        check_model_pair(None, normalizer, "generator")
        generator, normalizer, kind = load_base_generator(
            generator, checkpoint, device, sampling_steps
        )
    else:
        check_model_pair(generator, normalizer, "generator")
        if checkpoint is not None or sampling_steps is not None:
            raise ValueError(
                "checkpoint and sampling_steps go with generator=None or a kind name, "
                "not with a model object"
            )
        kind = generator_kind(generator)
    return generator.to(device).eval(), normalizer, kind


def resolve_avoid_steps(avoid_steps: int | None, avoid_step_size: float, kind: str) -> int:
    """The avoidance steps of a generator of ``kind``: ``avoid_steps``, or for None 20
    with MeanFlow and 0 with a diffusion generator (which has no one-step output to step
    on). ValueError naming the argument for a bad value."""
    from policies.learned.plan_avoidance import DEFAULT_AVOID_STEPS

    if avoid_steps is not None and (not is_integer(avoid_steps) or avoid_steps < 0):
        raise ValueError(f"avoid_steps must be None or an int >= 0, got {avoid_steps!r}")
    if not (is_number(avoid_step_size) and 0 < avoid_step_size < float("inf")):
        raise ValueError(f"avoid_step_size must be a finite number > 0, got {avoid_step_size!r}")
    if avoid_steps is None:
        return DEFAULT_AVOID_STEPS if kind == "meanflow" else 0
    if avoid_steps > 0 and kind != "meanflow":
        raise ValueError(f"avoid_steps > 0 needs the MeanFlow generator, got {kind!r}")
    return int(avoid_steps)


__all__ = [
    "resolve_avoid_steps",
    "resolve_generator",
    "DEFAULT_SAMPLING_STEPS",
    "GENERATOR_KINDS",
    "checkpoint_kind",
    "generator_kind",
    "load_base_generator",
]
