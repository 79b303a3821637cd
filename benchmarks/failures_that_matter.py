"""Failures that matter: how often each ego planner fails in a way it could have avoided.

Runs the default RiskFlow adversary (``riskflow``, K=5, target ``ego``) closed loop for
10 s against each planner of ``--planners`` on the first ``--scenes`` shipped evaluation
scenes (100 by default; or the scenes of ``--data``, a ScenarioNet or ``.npz`` folder, all
of them by default) for every seed of
``--seeds``, analyses every ego collision (:mod:`policies.stress.failures`) and prints
one row per planner: the avoidable-failure rate (the headline), the ego collision rate,
the share of ego collisions shown avoidable, strikes on a standing ego, guided vehicles
within 5 m at impact, attackers within the human p99 bounds, non-ego vehicles in contact,
the ego's progress (the counter-metric), and the coverage: the episodes with an attacker
and the share of the ego's steps below 2 m/s, where no attack starts. Below it, paired
differences of the avoidable-failure rate between consecutive planners (same scenes, same
seeds: McNemar,
:func:`policies.statistics.paired_difference`)::

    python benchmarks/failures_that_matter.py --scenes 100 --seeds 0 1 2
    python benchmarks/failures_that_matter.py --data ../shared/data/scenarionet --seeds 0 1 2

``oracle`` is the sampling MPC reading the adversary's own plans (privileged: what an
ideal planner avoids). Every episode's outcome is appended to ``--out`` (JSON Lines) as
it finishes and a rerun skips the episodes already there: a long run resumes where it
stopped (``--fresh`` starts over). ``--longer-search F`` re-runs the escape search of
every collision not shown avoidable with F times the budget and reports how many
verdicts flip.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from policies.cli_inputs import check_seeds
from policies.dataclass_cli import check_at_least, check_choices, run_main
from policies.evaluation.options import parse_k
from policies.harness import ClosedLoop
from policies.learned.guidance_losses import TARGETS
from policies.planners import PLANNERS, OraclePlanner, make_planner
from policies.registry import build_policy
from policies.statistics import paired_difference
from policies.stress import EscapeSearch, analyse, stress_summary
from policies.stress.summary import episode_outcome
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import shipped_bank
from riskflow_env.scenarios.folders import open_scenes

DEFAULT_SCENES = 100  # of the shipped evaluation bank
ROWS = (  # (label, summary key, scale, unit)
    ("avoidable failures", "avoidable_failure_rate", 100, "%"),
    ("ego collisions", "ego_collision_rate", 100, "%"),
    ("shown avoidable", "avoidable_share", 100, "%"),
    ("standing strikes", "standing_strike_share", 100, "%"),
    ("guided within 5 m", "attackers_at_impact", 1, ""),
    ("attacker plausible", "plausible_share", 100, "%"),
    ("into a wreck", "wreck_share", 100, "%"),
    ("non-ego in contact", "non_ego_contact_share", 100, "%"),
    ("ego progress [m]", "progress", 1, ""),
    ("ego collisions per km", "ego_collisions_per_km", 1, ""),
    ("episodes attacked", "attacked_rate", 100, "%"),
    ("ego steps below 2 m/s", "slow_ego_share", 100, "%"),
)


@dataclass(frozen=True)
class Options:
    """Options of ``failures_that_matter.py``."""

    planners: tuple[str, ...] = ("oracle", "sampling_mpc", "idm", "constant_velocity")
    """ego planners, best expected first: oracle or names of policies.planners.PLANNERS"""
    scenes: int | None = None
    """first N scenes of the shipped evaluation bank or of --data (default: 100 of the
    shipped bank, every scene of --data)"""
    data: Path | None = None
    """a ScenarioNet or .npz scene folder instead of the shipped bank"""
    seeds: tuple[int, ...] = (0,)
    """adversary noise seeds"""
    k: str = "5"
    """size of the controllable set: an int >= 0 or 'all'"""
    target: str = "ego"
    """what A_c is pulled toward"""
    steps: int = 100
    """episode length [steps of 0.1 s]"""
    longer_search: int = 0
    """re-search the collisions not shown avoidable with this many times the budget"""
    out: Path = Path("outputs/failures_that_matter.jsonl")
    """results file (JSON Lines, one episode a line; resumed)"""
    fresh: bool = False
    """start the results file over"""

    def __post_init__(self) -> None:
        lows = {"scenes": 1, "steps": 1, "longer_search": 0}
        check_at_least(self, lows, optional=("scenes",))
        object.__setattr__(self, "k", parse_k(str(self.k)))  # an int, or 'all'
        object.__setattr__(self, "seeds", check_seeds(self.seeds))
        check_choices(self, {"target": TARGETS})
        unknown = [p for p in self.planners if p != "oracle" and p not in PLANNERS]
        if unknown or not self.planners:
            names = ("oracle", *PLANNERS)
            raise ValueError(f"--planners: expected names of {names}, got {unknown}")
        if self.out.is_dir():
            raise ValueError(f"--out {self.out} is a folder; give a .jsonl file")

    def settings(self) -> dict[str, Any]:
        """What an episode's outcome depends on besides (planner, scene, seed): every row
        records it, and a results file of other settings is not resumed."""
        data = "shipped:eval" if self.data is None else str(self.data)
        return {"data": data, "k": self.k, "target": self.target, "steps": self.steps,
                "longer_search": self.longer_search}  # fmt: skip


def scenes(options: Options) -> list:
    """The scenes to run; ValueError naming ``--scenes`` when the source holds fewer."""
    source = shipped_bank("eval") if options.data is None else open_scenes(options.data)
    count = options.scenes or (DEFAULT_SCENES if options.data is None else len(source))
    if count > len(source):
        where = "the shipped evaluation bank" if options.data is None else f"--data {options.data}"
        raise ValueError(f"--scenes {count}: {where} holds only {len(source)} scenes")
    return [source[index] for index in range(count)]


def resumed(options: Options) -> dict[tuple, dict[str, Any]]:
    """The episodes already in ``--out``; ValueError when they were run with other settings."""
    done = {}
    settings = options.settings()
    lines = options.out.read_text().splitlines()
    for number, line in enumerate(lines, 1):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            if number == len(lines):
                continue  # a line cut by an interrupted write: run that episode again
            raise ValueError(f"--out {options.out}: line {number} is not JSON") from None
        if row.get("settings") != settings:
            there = row.get("settings") or "not recorded"
            raise ValueError(
                f"--out {options.out} holds episodes of other settings ({there} there, "
                f"{settings} now); give another --out, or --fresh to start it over"
            )
        done[(row["planner"], row["scene"], row["seed"])] = row
    return done


def run_episode(planner_name: str, scenario, seed: int, options: Options) -> dict[str, Any]:
    """One episode of ``planner_name`` against the default adversary, analysed."""
    policy = build_policy(
        "riskflow", {}, k=options.k, planning_interval=0.5, target=options.target, seed=seed
    )
    planner = OraclePlanner(policy) if planner_name == "oracle" else make_planner(planner_name)
    with ClosedLoop(planner, policy, EnvConfig(episode_steps=options.steps)) as loop:
        record = loop.run(scenario)
    failures = analyse(record)
    outcome = episode_outcome(record, failures)
    if options.longer_search:
        longer = EscapeSearch().scaled(options.longer_search)
        again = analyse(record, search=longer)
        outcome["longer_search_flips"] = sum(
            f.searched and not f.avoidable and g.avoidable
            for f, g in zip(failures, again, strict=True)
        )
    return outcome


def main(options: Options) -> dict[str, Any]:
    """Run (or resume) every episode, print the table; returns the summaries."""
    if options.fresh and options.out.exists():
        options.out.unlink()
    options.out.parent.mkdir(parents=True, exist_ok=True)
    done = resumed(options) if options.out.exists() else {}
    bank = scenes(options)
    jobs = [
        (planner, index, seed)
        for planner in list(options.planners)
        for index in range(len(bank))
        for seed in list(options.seeds)
        if (planner, index, seed) not in done
    ]
    with options.out.open("a") as results:
        for planner, index, seed in tqdm(jobs, desc="episodes"):
            row = {"planner": planner, "scene": index, "seed": seed}
            row["settings"] = options.settings()
            row |= run_episode(planner, bank[index], seed, options)
            results.write(json.dumps(row) + "\n")
            results.flush()
            done[(planner, index, seed)] = row
    return report(done, options, len(bank))


def report(done: dict, options: Options, num_scenes: int) -> dict[str, Any]:
    """Print the table and the paired differences of the first ``num_scenes`` scenes;
    returns the summaries."""
    planners = list(options.planners)
    keys = [(index, seed) for index in range(num_scenes) for seed in list(options.seeds)]
    rows = {p: [done[(p, *key)] for key in keys if (p, *key) in done] for p in planners}
    summaries = {planner: stress_summary(rows[planner]) for planner in planners}
    print(f"RiskFlow K={options.k} target={options.target}, {len(keys)} episodes per planner")
    print(f"{'':22s}" + "".join(f"{p:>24s}" for p in planners))
    for label, key, scale, unit in ROWS:
        cells = []
        for planner in planners:
            entry = summaries[planner][key]
            if entry["value"] is None:
                cells.append("n/a")
                continue
            text = f"{scale * entry['value']:.1f}{unit}"
            if entry["low"] is not None:
                text += f" [{scale * entry['low']:.0f},{scale * entry['high']:.0f}]"
            cells.append(text)
        print(f"{label:22s}" + "".join(f"{cell:>24s}" for cell in cells))
    for planner in planners:  # results files written before the coverage fields lack them
        covered = summaries[planner]["attacked_rate"]["n"]
        if covered < len(rows[planner]):
            print(f"  {planner}: coverage over {covered} of {len(rows[planner])} episodes")
    flips = [sum(r.get("longer_search_flips", 0) for r in rows[p]) for p in planners]
    if options.longer_search:
        print(f"{'longer search flips':22s}" + "".join(f"{f:>24d}" for f in flips))
    for better, worse in zip(planners, planners[1:], strict=False):
        pairs = [
            (_avoidable(done[(better, *k)]), _avoidable(done[(worse, *k)]))
            for k in keys
            if (better, *k) in done and (worse, *k) in done
        ]
        counts = {
            "n": len(pairs),
            "trained_only": sum(a and not b for a, b in pairs),
            "untrained_only": sum(b and not a for a, b in pairs),
        }
        diff = paired_difference(counts)
        print(
            f"{better} - {worse}: avoidable-failure rate {100 * diff['difference']:+.1f} pts "
            f"[{100 * diff['low']:+.1f}, {100 * diff['high']:+.1f}], McNemar p = "
            f"{diff['p_value']:.3g} (n = {len(pairs)})"
        )
    return summaries


def _avoidable(row: dict[str, Any]) -> bool:
    return any(failure["avoidable"] for failure in row["failures"])


if __name__ == "__main__":
    run_main(main, Options, "failures_that_matter.py", __doc__.splitlines()[0])
