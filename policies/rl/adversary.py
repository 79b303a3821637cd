"""The traffic an RL ego trains and is evaluated against, and its curriculum stages.

:class:`ScenePolicyConfig` names a scene policy for the non-ego vehicles (the RiskFlow
adversary, the unguided generator, IDM) with the few options RL training varies;
:func:`make_traffic` builds it. :class:`AdversaryStage` is one point of a curriculum
(``k``, guidance strength ``lambda_adv``, ``target``); :func:`apply_stage` sets it on a
live :class:`~policies.riskflow.RiskFlowAdversary` between episodes (the next planning
cycle uses it), which is how the training callback ramps the adversary in every worker
(``VecEnv.env_method("set_adversary_stage", stage)``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from policies.dataclass_cli import check_at_least
from policies.learned.guidance_losses import TARGETS
from policies.learned.ranking import check_k
from riskflow_env.view import ScenePolicy

TRAFFIC_KINDS = ("riskflow", "idm", "replay")


@dataclass(frozen=True)
class AdversaryStage:
    """Adversary settings of one curriculum stage.

    Attributes:
        k: size of the controllable set ``A_c`` (0: the unguided generator).
        lambda_adv: adversarial guidance weight [1/m]; larger is more adversarial.
        target: ``"others"`` (the paper's: pull toward any non-controllable vehicle, the
            ego included) or ``"ego"`` (pull toward the ego only).
    """

    k: int = 5
    lambda_adv: float = 50.0
    target: str = "others"

    def __post_init__(self) -> None:
        check_k(self.k)
        if self.target not in TARGETS:
            raise ValueError(f"AdversaryStage.target must be one of {TARGETS}, got {self.target!r}")
        if not self.lambda_adv >= 0:
            raise ValueError(f"AdversaryStage.lambda_adv must be >= 0, got {self.lambda_adv}")


@dataclass(frozen=True)
class ScenePolicyConfig:
    """The scene policy of the non-ego vehicles.

    Attributes:
        kind: ``"riskflow"`` (the RiskFlow generator; ``stage.k = 0`` is the unguided
            generator, nominal traffic), ``"idm"`` (IDM car following, nominal traffic) or
            ``"replay"`` (every vehicle tracks its logged trajectory: recorded traffic, which
            does not react to the ego).
        stage: k, guidance weight and target of the RiskFlow adversary.
        guidance_steps: ``K_g`` guidance steps per planning cycle (default 30).
        planning_interval: time between re-plans [s] (default 0.5).
        device: torch device of the RiskFlow adversary ("cpu", or "cuda" where a GPU is
            present: worth it with many scenes per planning call, ``EgoVectorEnv``).
    """

    kind: str = "riskflow"
    stage: AdversaryStage = dataclasses.field(default_factory=AdversaryStage)
    guidance_steps: int = 30
    planning_interval: float = 0.5
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.kind not in TRAFFIC_KINDS:
            raise ValueError(
                f"ScenePolicyConfig.kind must be one of {TRAFFIC_KINDS}, got {self.kind!r}"
            )
        check_at_least(self, {"guidance_steps": 0}, owner="ScenePolicyConfig")
        if not self.planning_interval > 0:
            raise ValueError(
                f"ScenePolicyConfig.planning_interval must be > 0 s, got {self.planning_interval}"
            )

    @property
    def label(self) -> str:
        """Short name for tables: ``riskflow K=5``, ``riskflow K=0``, ``idm``, ``replay``;
        ``riskflow K=5 ego`` for the target ``ego``."""
        if self.kind != "riskflow":
            return self.kind
        return f"riskflow K={self.stage.k}" + (" ego" if self.stage.target == "ego" else "")


def make_traffic(config: ScenePolicyConfig, seed: int = 0, generator=None, normalizer=None):
    """The scene policy of ``config`` (the RiskFlow adversary loads the shipped checkpoint
    unless ``generator`` and ``normalizer`` are given).

    Args:
        config: which traffic.
        seed: the adversary's noise seed.
        generator: a RiskFlow generator to use instead of the shipped one.
        normalizer: its action normaliser.
    """
    from policies.registry import build_policy

    if config.kind != "riskflow":  # idm, replay: nothing to configure
        return build_policy(
            config.kind, {}, k=None, planning_interval=None, target="others", seed=seed
        )
    stage = config.stage
    options = {"lambda_adv": stage.lambda_adv, "guidance_steps": config.guidance_steps}
    if generator is not None:
        options |= {"generator": generator, "normalizer": normalizer}
    return build_policy(
        "riskflow",
        options,
        k=stage.k,
        planning_interval=config.planning_interval,
        target=stage.target,
        seed=seed,
        device=config.device,
    )


def apply_stage(policy: ScenePolicy, stage: AdversaryStage) -> None:
    """Set ``stage`` on a RiskFlow adversary (in place; takes effect at its next cycle).

    Raises:
        TypeError: ``policy`` has no guidance (IDM traffic has no adversary to ramp).
    """
    guidance = getattr(policy, "guidance", None)
    if guidance is None or not hasattr(policy, "k"):
        raise TypeError(
            f"apply_stage needs a RiskFlow adversary (with k and guidance), "
            f"got {type(policy).__name__}"
        )
    policy.k = check_k(stage.k)
    policy.guidance = dataclasses.replace(
        guidance, lambda_adv=float(stage.lambda_adv), target=stage.target
    )
