"""What a training run starts from and saves besides the weights: its options as plain
values, the random state that ``--resume`` restores, and the action statistics."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from policies.learned.checkpoint import normalizer_of
from policies.learned.data import ActionNormalizer, WindowDataset, compute_action_stats
from policies.learned.data import load_or_compute_stats as action_stats
from policies.learned.generator import RiskFlowGenerator
from policies.learned.train_options import LoopOptions


def plain_options(options: LoopOptions) -> dict[str, Any]:
    """``options`` as JSON-ready values (paths as strings, tuples as lists): a
    checkpoint's ``train_config``."""

    def plain(value: Any) -> Any:
        if isinstance(value, tuple):
            return [plain(item) for item in value]
        return str(value) if isinstance(value, Path) else value

    return {key: plain(value) for key, value in vars(options).items()}


# What a resumed run may change: how long it goes on, where it runs, how often it reports.
# The data folders may have moved; everything else would be another training.
RESUMABLE = frozenset({
    "steps", "stop_step", "time_budget_min", "threads", "device", "resume", "out", "init",
    "eval_every", "log_every", "val_windows", "num_samples", "data", "val_data", "processes",
})  # fmt: skip


def check_resume(options: Any, saved: dict[str, Any], kind: str) -> None:
    """ValueError naming the flags of ``options`` that differ from the training state
    ``saved`` (a checkpoint's ``train_config``) outside :data:`RESUMABLE`: a resumed run
    goes on with the same training, or ``--resume``'s promise of the uninterrupted result
    breaks silently. The model is the checkpoint's (its loader names an architecture that
    differs)."""
    now = plain_options(options) | {"generator": kind}
    skip = RESUMABLE | {"model"}
    changed = [key for key in now if key not in skip and key in saved and saved[key] != now[key]]
    if changed:
        flags = ", ".join(
            f"--{key.replace('_', '-')} {saved[key]!r} there, {now[key]!r} now" for key in changed
        )
        raise ValueError(
            f"--resume: {options.out} was trained with other options ({flags}); a resumed run "
            "continues the same training: drop them, or train into another --out"
        )


def rng_state(noise: torch.Generator) -> dict[str, Any]:
    """The random state a resumed run restores: ``noise`` (the run's draws), torch's
    and numpy's global generators."""
    _, key, position, has_gauss, gauss = np.random.get_state()  # noqa: NPY002
    numpy = {"key": torch.from_numpy(key.astype(np.int64)), "pos": int(position)}
    numpy |= {"has_gauss": int(has_gauss), "gauss": float(gauss)}
    return {"noise": noise.get_state(), "torch": torch.get_rng_state(), "numpy": numpy}


def set_rng_state(noise: torch.Generator, state: dict[str, Any]) -> None:
    """Restore :func:`rng_state`'s ``state``."""
    noise.set_state(state["noise"].cpu())
    torch.set_rng_state(state["torch"].cpu())
    numpy = state["numpy"]
    key = numpy["key"].cpu().numpy().astype(np.uint32)
    np.random.set_state(("MT19937", key, numpy["pos"], numpy["has_gauss"], numpy["gauss"]))  # noqa: NPY002


def initial_normalizer(
    options: LoopOptions,
    state: dict[str, Any],
    start: tuple[RiskFlowGenerator, ActionNormalizer] | None,
    train_set: WindowDataset,
) -> ActionNormalizer:
    """The action statistics: the resumed checkpoint's, ``--init``'s, or the training
    split's (cached beside one folder's scenes; several folders: computed, fast)."""
    if state:
        return normalizer_of(state)
    if start is not None:
        return start[1]
    if len(options.data) == 1:
        return action_stats(options.data[0], train_set)
    return compute_action_stats(train_set)


__all__ = ["initial_normalizer", "plain_options", "rng_state", "set_rng_state"]
