"""One stress-test episode: the planner under test against the RiskFlow adversary, analysed.

:class:`EpisodeSetup` holds everything that fixes an episode besides the scene, the
adversary's noise seed and the planner: the adversary's options, the episode length and
the device. :class:`EpisodeRunner` runs episodes of one planner (:func:`run_episode`):
the adversary is reseeded before each (so that an episode depends on its scene and seed
only, never on the episodes run before it in the same process), the whole episode and its
failure analysis run on one torch thread (a worker process's setting, so that the worker
count never changes a number), and every ego collision is analysed
(:func:`policies.stress.failures.analyse`). The same episode run again, by a worker, by
the parent or by ``riskflow-stress replay``, is the same bit for bit, as long as the planner
is deterministic and its ``reset(view)`` forgets the previous episode.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from policies.cli_inputs import DT, check_interval
from policies.harness import ClosedLoop
from policies.learned.adversary_config import HORIZON_S
from policies.learned.checkpoint import DEFAULT_NAME, load_checkpoint
from policies.learned.guidance_losses import TARGETS
from policies.planners import EgoPlanner
from policies.riskflow import RiskFlowAdversary
from policies.stress.failures import analyse
from policies.stress.summary import Analysed
from riskflow_env.config import EnvConfig, is_integer
from riskflow_env.scenarios import Scenario
from riskflow_env.view import ScenePolicy

SHIPPED_CHECKPOINT = Path(__file__).resolve().parents[1] / "checkpoints" / DEFAULT_NAME


@dataclass(frozen=True)
class EpisodeSetup:
    """The adversary and the episode, as a stress test runs them."""

    k: str = "5"
    """size of the adversary's controllable set A_c: an int >= 0 or 'all'"""
    target: str = "ego"
    """what A_c is pulled toward: 'ego' (stress testing) or 'others' (the paper's)"""
    planning_interval: float = 0.5
    """time between re-plans of the adversary [s], a multiple of 0.1 s up to 5.2 s"""
    steps: int = 100
    """episode length [steps of 0.1 s]; an ego collision or off-road ends it earlier"""
    device: str = "cpu"
    """torch device of the adversary's generator"""
    checkpoint: Path | None = None
    """generator checkpoint; default the shipped policies/checkpoints/riskflow_default.pt"""

    def __post_init__(self) -> None:
        k = str(self.k)
        if not (k == "all" or k.isdigit()):
            raise ValueError(f"--k must be an int >= 0 or 'all', got {self.k!r}")
        object.__setattr__(self, "k", k)
        if self.target not in TARGETS:
            raise ValueError(f"--target must be one of {TARGETS}, got {self.target!r}")
        if not is_integer(self.steps) or self.steps < 1:
            raise ValueError(f"--steps must be an int >= 1 [steps of 0.1 s], got {self.steps!r}")
        object.__setattr__(self, "steps", int(self.steps))  # a numpy int as a Python one
        horizon = HORIZON_S if self.checkpoint is None else None  # another's: when read
        check_interval(self.planning_interval, DT, horizon, "--planning-interval")
        if self.checkpoint is not None:
            object.__setattr__(self, "checkpoint", Path(self.checkpoint))
            if self.checkpoint.is_dir():
                raise ValueError(f"--checkpoint: {str(self.checkpoint)!r} is a folder, not a file")
            if not self.checkpoint.is_file():
                raise ValueError(f"--checkpoint: no such file {str(self.checkpoint)!r}")

    def check_checkpoint(self) -> None:
        """Read ``checkpoint`` once (the shipped one is not read); a ValueError naming
        ``--checkpoint`` when it is not a generator checkpoint, or ``--planning-interval``
        when the interval exceeds its plans' horizon."""
        if self.checkpoint is None:
            return
        try:
            config = load_checkpoint(self.checkpoint).get("config")
        except ValueError as err:  # CheckpointError included
            raise ValueError(f"--checkpoint: {err}") from None
        steps = config.get("future_steps") if isinstance(config, dict) else None
        if isinstance(steps, int):
            check_interval(self.planning_interval, DT, steps * DT, "--planning-interval")

    def adversary(self, seed: int = 0) -> RiskFlowAdversary:
        """The RiskFlow adversary of this setup, with noise seed ``seed``."""
        return RiskFlowAdversary(
            k=self.k if self.k == "all" else int(self.k),
            planning_interval=self.planning_interval,
            target=self.target,
            seed=seed,
            device=self.device,
            checkpoint=self.checkpoint,
        )

    def env_config(self) -> EnvConfig:
        """The env of the episodes (the defaults but the length)."""
        return EnvConfig(episode_steps=self.steps)

    def checkpoint_sha256(self) -> str:
        """16 hex digits of the generator file's SHA-256 (the shipped one by default)."""
        path = self.checkpoint or SHIPPED_CHECKPOINT
        return hashlib.sha256(path.read_bytes()).hexdigest()[:16]

    def as_json(self) -> dict[str, Any]:
        """The fields, JSON-ready (paths as strings)."""
        return {
            name: str(value) if isinstance(value, Path) else value
            for name, value in dataclasses.asdict(self).items()
        }

    @classmethod
    def from_json(cls, values: dict[str, Any]) -> EpisodeSetup:
        """The setup of :meth:`as_json` (other keys ignored)."""
        names = {field.name for field in dataclasses.fields(cls)}
        return cls(**{name: value for name, value in values.items() if name in names})


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """torch on one CPU thread inside the block (the previous count restored after)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def run_episode(
    loop: ClosedLoop, adversary: RiskFlowAdversary, scenario: Scenario, seed: int
) -> Analysed:
    """One episode of ``loop`` from ``scenario`` with the adversary reseeded to ``seed``,
    and its failures (module docstring)."""
    with one_thread():
        adversary.reseed(seed)
        record = loop.run(scenario)
        loop.records.clear()  # the caller keeps what it needs
        return Analysed(record, analyse(record))


class EpisodeRunner:
    """Episodes of one planner against the adversary of ``setup`` (module docstring).

    Args:
        planner: the planner under test.
        setup: the adversary and episode options.
        policy: wraps the adversary before the loop gets it (e.g. to draw on a video);
            None: the adversary itself.
        video: video file of the episodes (``ClosedLoop``'s ``video``).
    """

    def __init__(
        self,
        planner: EgoPlanner,
        setup: EpisodeSetup,
        policy: Any = None,
        video: str | Path | None = None,
        render_config: Any = None,
    ) -> None:
        self.setup = setup
        self.adversary = setup.adversary()
        scene_policy: ScenePolicy = self.adversary if policy is None else policy(self.adversary)
        self.loop = ClosedLoop(
            planner, scene_policy, config=setup.env_config(), video=video,
            render_config=render_config,
        )  # fmt: skip

    def __call__(self, scenario: Scenario, seed: int) -> Analysed:
        """One episode from ``scenario`` with adversary seed ``seed``."""
        return run_episode(self.loop, self.adversary, scenario, seed)

    def close(self) -> None:
        """Close the loop (and its video)."""
        self.loop.close()

    def __enter__(self) -> EpisodeRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["EpisodeRunner", "EpisodeSetup", "one_thread", "run_episode"]
