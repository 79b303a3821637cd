"""Evaluate trained PPO egos against the IDM planner, lane keeping, a sampling MPC, constant
velocity and random actions (and, with ``--oracle``, the MPC reading the adversary's plans).

    python examples/evaluate_ego.py --runs runs/ego_ppo/seed0,runs/ego_ppo/seed1,runs/ego_ppo/seed2

``--runs`` takes training run folders (``train_ego_ppo.py --out``; an interrupted run
without ``final_model.zip`` is evaluated at its latest checkpoint, which is printed) or
model files, with or without ``.zip`` (``RUN/checkpoints/ppo_N_steps``). A path that is
not one of those is one line naming ``--runs`` (or ``--model``) and what was expected.

Every ego drives the same scenes of the shipped *evaluation* bank (the PPO egos trained
on the training bank), or of ``--data`` (a ScenarioNet folder or a folder of ``.npz``
scenes: recorded traffic), under the RiskFlow adversary at its defaults (K=5, 30 guidance
steps, re-plan every 0.5 s, target ``others``) and each nominal traffic of ``--nominal``
(the unguided generator, K=0; IDM; log replay). Each PPO run contributes its
trained policy (``final_model.zip`` or ``--model``; rows ``ppo`` or ``--label``) and its
untrained initial policy (``initial_model.zip``; rows ``ppo-initial``), both acting with
the Gaussian's mean (maneuver actions: the most probable maneuver among those the action
mask allows, ``--no-mask-actions`` for the raw policy's choice); a run is evaluated
with its own seed (adversary noise: ``seed * 100 + i``, ``i < --episodes-per-run``), the
baselines with every seed of ``--seeds``. Episodes: 10 s, ending at an ego collision or
off-road (the library's default ``EnvConfig``).

Report: ego collision rate, off-road rate, collision-or-off-road rate (Wilson 95%
intervals over all (seed, scene) episodes), progress [m] and time to the first ego
collision [s] (bootstrap 95% intervals), as a Markdown table (``<out>/results.md``,
printed), a plot (``<out>/results.png``) and JSON (``<out>/results.json``, with a
per-run breakdown of the PPO rows), the trained-vs-untrained comparison on paired
episodes (:mod:`policies.rl.paired`; with ``--paired``, each trained ego against each
baseline too) and the runs' training curves (``<out>/training.png``).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from policies.cli_inputs import open_data, parse_seeds
from policies.dataclass_cli import check_at_least, check_choices, parse_dataclass
from policies.learned.adversary_config import check_planning_interval
from policies.planners import OraclePlanner, make_planner
from policies.rl.adversary import TARGETS, AdversaryStage, ScenePolicyConfig
from policies.rl.combine import load_results
from policies.rl.envs import interface_options
from policies.rl.evaluation import RandomPlanner, evaluate, load_ppo_planner, summarize_ego
from policies.rl.paired import PAIRED_OUTCOMES, paired_counts
from policies.rl.report import markdown_table, paired_table, plot_summaries, plot_training
from policies.rl.runs import INITIAL, RunError, RunModel, check_model_file, find_model, read_options
from riskflow_env.atomic_files import write_text
from riskflow_env.cli_errors import debug_requested, user_errors
from riskflow_env.config import EnvConfig
from riskflow_env.folder_lock import make_output_folder
from riskflow_env.scenarios import SPLITS, shipped_bank

NOMINAL = ("generator", "idm", "replay")
BASELINES = {
    **{
        name: lambda seed, name=name: make_planner(name)
        for name in ("idm", "lane_keeping", "sampling_mpc", "constant_velocity")
    },
    "random": lambda seed: RandomPlanner(seed),
}


@dataclass(frozen=True)
class Options:
    """Options of evaluate_ego.py."""

    runs: str = ""
    """comma-separated training run folders (train_ego_ppo.py --out) or model files (with or
    without .zip); empty: baselines only"""
    label: str = "ppo"
    """name of the PPO rows ('<label>' trained, '<label>-initial' untrained)"""
    model: str = "final_model"
    """model of each run folder to evaluate as 'ppo', with or without .zip (e.g.
    checkpoints/ppo_80000_steps); final_model of an interrupted run: its latest checkpoint"""
    out: Path = Path("outputs/evaluate_ego")
    """output folder"""
    split: str = "eval"
    """shipped scenario bank (without --data)"""
    data: str | None = None
    """scenes from a ScenarioNet dataset folder or a folder of .npz scenes instead of the
    shipped bank (e.g. recorded nuScenes scenes)"""
    scenes: int = 35
    """number of scenes, spread evenly over the bank (every family)"""
    seeds: str = "0,1,2"
    """seeds of the baselines' runs (a PPO run uses its own training seed)"""
    episodes_per_run: int = 1
    """adversary seeds per PPO run (seed*100 + i): more episodes per scene"""
    nominal: str = "generator"
    """comma-separated nominal traffics, of 'generator' (unguided, K=0), 'idm' and 'replay'
    (log replay: the recorded trajectories)"""
    k: int = 5
    """K of the adversarial traffic"""
    target: str = "others"
    """guidance target of the adversarial traffic: 'others' (the paper's) or 'ego' (rows
    'riskflow K=5 ego')"""
    paired: bool = False
    """evaluate every PPO run on the baselines' --seeds too (each seed x --episodes-per-run
    ignored), so that every ego drives the same (scene, adversary seed) episodes; the
    report then pairs each trained ego with each baseline as well"""
    guidance_steps: int = 30
    """K_g of the adversarial traffic"""
    planning_interval: float = 0.5
    """re-plan interval of both RiskFlow traffics [s]"""
    episode_steps: int = 100
    """episode length [steps of 0.1 s]"""
    baselines: bool = True
    """also evaluate the IDM, lane-keeping, sampling-MPC, constant-velocity and random egos"""
    planners: str = ""
    """comma-separated baselines to evaluate, of idm, lane_keeping, sampling_mpc,
    constant_velocity, random (e.g. 'sampling_mpc'); empty: all of them"""
    oracle: bool = False
    """also evaluate the oracle (sampling MPC that reads the adversary's plans: what is
    avoidable; needs RiskFlow nominal traffic)"""
    mask_actions: bool = True
    """PPO egos with maneuver actions choose among the maneuvers the action mask allows (those
    that keep the ego on the road over the next second: a safety filter at deployment);
    --no-mask-actions: the raw policy"""
    trust_model: bool = False
    """load the --runs PPO models although SB3 model files are pickles that can run code
    (required with --runs; only for files you trust, docs/reference/security.md)"""
    combine: str = ""
    """comma-separated results.json files of earlier runs: merge them (no new episodes)"""

    def __post_init__(self) -> None:
        nominal = self.nominal_names()
        if not nominal or not set(nominal) <= set(NOMINAL):
            raise ValueError(
                f"--nominal must be a comma-separated list of {NOMINAL}, got {self.nominal!r}"
            )
        if self.oracle and nominal != ["generator"]:
            raise ValueError("--oracle reads the traffic's plans: it needs --nominal generator")
        if self.runs and not self.trust_model:
            raise ValueError(
                "--runs loads stable-baselines3 model files, which are pickles that can run "
                "arbitrary code: add --trust-model if you trust them (docs/reference/security.md)"
            )
        check_choices(self, {"target": TARGETS, "split": SPLITS})
        unknown = sorted(set(self.planner_names()) - set(BASELINES))
        if unknown:
            raise ValueError(
                f"--planners: unknown baseline(s) {unknown}; expected names of {list(BASELINES)}"
            )
        lows = {"scenes": 1, "episodes_per_run": 1, "episode_steps": 1, "k": 0}
        check_at_least(self, {**lows, "guidance_steps": 0})
        check_planning_interval(self.planning_interval)
        self.seed_list()  # checks --seeds

    def seed_list(self) -> list[int]:
        """The baselines' seeds of ``--seeds`` (comma- or space-separated distinct ints >= 0)."""
        return list(parse_seeds(self.seeds))

    def nominal_names(self) -> list[str]:
        """The nominal traffics of ``--nominal``, in order, each once."""
        names = [name.strip() for name in self.nominal.split(",") if name.strip()]
        return list(dict.fromkeys(names))

    def planner_names(self) -> list[str]:
        """The baselines of ``--planners`` (empty: every one of ``BASELINES``)."""
        names = [name.strip() for name in self.planners.split(",") if name.strip()]
        return names or list(BASELINES)


def run_options(run: Path) -> tuple[int, dict]:
    """Training seed of a run folder and the options its policy needs at evaluation (base
    planner, action repeat, maneuver features and actions), from its options.json."""
    options = read_options(run)
    return int(options["seed"]), interface_options(options)


def spread_scenes(bank, count: int) -> list:
    """``count`` scenes of ``bank`` spread evenly over it (every family; all if fewer)."""
    count = min(count, len(bank))
    return [bank[round(i * len(bank) / count)] for i in range(count)]


def ppo_factory(path: Path, policy: dict, mask_actions: bool = True):
    """``factory(seed)`` of the PPO planner saved at ``path`` (deterministic actions; with
    ``mask_actions``, maneuvers chosen among those the action mask allows)."""
    return lambda seed: load_ppo_planner(
        str(path), True, **policy, trusted=True, mask_actions=mask_actions
    )


def find_runs(options: Options) -> list[tuple[RunModel, Path]]:
    """(trained model and its run, untrained model) of every ``--runs`` entry, each loaded
    once to check it; a RunError naming the entry when one is not what it should be."""
    found = []
    for entry in [r for r in options.runs.split(",") if r]:
        chosen = find_model(entry, options.model)
        if chosen.note:
            print(chosen.note)
        initial = chosen.run / f"{INITIAL}.zip"
        if not initial.is_file():
            raise RunError(f"--runs {entry}: no {initial} (the untrained policy of the run)")
        _, policy = run_options(chosen.run)
        for path in (chosen.model, initial):
            try:
                check_model_file(path, "--runs")
                ppo_factory(path, policy)(0)
            except RunError:
                raise
            except Exception as error:  # whatever SB3 raises on a broken or foreign file
                raise RunError(
                    f"--runs {entry}: cannot load {path} as this run's policy "
                    f"({type(error).__name__}: {error})"
                ) from None
        found.append((chosen, initial))
    return found


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(Options, argv, prog=PROG, description=__doc__, debug=True)
    try:
        runs = find_runs(options)
        if not (runs or options.combine or options.oracle or options.baselines):
            raise ValueError("nothing to evaluate: give --runs or --oracle, or drop --no-baselines")
        combined = load_results(options.combine) if options.combine else None
        if combined is None:
            bank = shipped_bank(options.split) if options.data is None else open_data(options.data)
            if options.scenes > len(bank):  # e.g. the default 35 on a small --data folder
                print(f"--scenes {options.scenes}: evaluating all {len(bank)} scenes there are")
        make_output_folder(options.out)  # before any episode runs
    except ValueError as error:  # RunError included
        print(f"evaluate_ego.py: error: {error}", file=sys.stderr)
        sys.exit(2)
    if combined is not None:
        summaries, per_run, paired, mask_actions, episodes = combined
        stage = AdversaryStage(k=options.k, target=options.target)
        label = ScenePolicyConfig(stage=stage).label
        write_report(summaries, per_run, paired, label, options.out, mask_actions, episodes)
        return
    scenes = spread_scenes(bank, options.scenes)
    config = EnvConfig(episode_steps=options.episode_steps)
    adversarial = ScenePolicyConfig(
        stage=AdversaryStage(k=options.k, target=options.target),
        guidance_steps=options.guidance_steps,
        planning_interval=options.planning_interval,
    )
    nominal = {
        "generator": ScenePolicyConfig(
            stage=AdversaryStage(k=0), planning_interval=options.planning_interval
        ),
        "idm": ScenePolicyConfig(kind="idm"),
        "replay": ScenePolicyConfig(kind="replay"),
    }
    traffics = (adversarial, *(nominal[name] for name in options.nominal_names()))
    names = options.planner_names() if options.baselines else []
    baselines = {name: BASELINES[name] for name in names}
    if options.oracle:
        baselines["oracle"] = lambda seed: OraclePlanner()
    baseline_seeds = options.seed_list()
    run_episodes = len(baseline_seeds) if options.paired else options.episodes_per_run
    episodes = (
        len(traffics)
        * len(scenes)
        * (len(runs) * 2 * run_episodes + len(baselines) * len(baseline_seeds))
    )
    bar = tqdm(total=episodes, desc="episodes", unit="episode")

    def advance(label: str) -> None:
        """``evaluate``'s progress callback: one episode ran."""
        bar.set_postfix_str(label, refresh=False)
        bar.update()

    results, per_run, paired, seeds_of, trained_eps = {}, {}, [], {}, []
    for chosen, initial in runs:
        seed, policy = run_options(chosen.run)
        seeds = [seed * 100 + i for i in range(options.episodes_per_run)]
        seeds = baseline_seeds if options.paired else seeds
        planners = {
            options.label: ppo_factory(chosen.model, policy, options.mask_actions),
            f"{options.label}-initial": ppo_factory(initial, policy, options.mask_actions),
        }
        records = evaluate(planners, traffics, scenes, seeds, config, progress=advance)
        for (name, traffic), episodes in records.items():
            results.setdefault((name, traffic), []).extend(episodes)
            per_run[f"{name} (seed {seed})", traffic] = summarize_ego(episodes)
            seeds_of[f"{name} (seed {seed})"] = seeds
        for traffic in traffics:
            trained, untrained = (records[name, traffic.label] for name in planners)
            trained_eps.append((seed, traffic.label, trained))
            for metric in PAIRED_OUTCOMES:
                counts = paired_counts(trained, untrained, metric)
                row = {"planner": options.label, "run": f"seed {seed}", "traffic": traffic.label}
                paired.append(row | {"metric": metric, **counts})
    if baselines:
        results |= evaluate(baselines, traffics, scenes, baseline_seeds, config, progress=advance)
        seeds_of |= dict.fromkeys(baselines, baseline_seeds)
    if options.paired:  # every trained ego against every baseline, on the same episodes
        for seed, traffic, trained in trained_eps:
            for name in baselines:
                row = {"planner": f"{options.label} vs {name}", "run": f"seed {seed}"}
                row |= {"traffic": traffic, "reference": name}
                for metric in PAIRED_OUTCOMES:
                    counts = paired_counts(trained, results[name, traffic], metric)
                    paired.append(row | {"metric": metric, **counts})
    bar.close()

    summaries = {key: summarize_ego(episodes) for key, episodes in results.items()}
    mask_actions = options.mask_actions if runs else None
    episodes = {"scenes": [scene.name for scene in scenes], "seeds": seeds_of}
    label = adversarial.label
    write_report(summaries, per_run, paired, label, options.out, mask_actions, episodes)
    curves = {f"seed {run_options(chosen.run)[0]}": chosen.run for chosen, _ in runs}
    if curves:
        plot_training(curves, options.out / "training.png")
        print(f"written: {options.out / 'training.png'}")


def write_report(
    summaries: dict,
    per_run: dict,
    paired: list,
    adversarial_label: str,
    out: Path,
    mask_actions: bool | None = None,
    episodes: dict | None = None,
) -> None:
    """results.md (printed), results.png and results.json; adversarial rows first;
    ``mask_actions``: how the PPO egos chose their maneuvers (None: no PPO rows);
    ``episodes``: the scenes and each row's seeds (what ``--combine`` checks for overlap)."""
    order = sorted(summaries, key=lambda key: (key[1] != adversarial_label, key[1]))
    summaries = {key: summaries[key] for key in order}
    sections = [markdown_table(summaries)]
    versus = [row for row in paired if "reference" in row]  # trained vs a baseline
    paired = [row for row in paired if "reference" not in row]
    if paired:
        sections.append("Trained vs untrained, paired episodes:\n\n" + paired_table(paired))
    if versus:
        table = paired_table(versus, reference="baseline")
        sections.append("Trained vs each baseline, paired episodes:\n\n" + table)
    if per_run:
        sections.append("Per run:\n\n" + markdown_table(per_run))
    text = "\n\n".join(sections)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "results.md", text + "\n")
    plot_summaries(summaries, out / "results.png")
    rows = [{"planner": p, "traffic": t, **s} for (p, t), s in summaries.items()]
    runs = [{"planner": p, "traffic": t, **s} for (p, t), s in per_run.items()]
    content = {"summary": rows, "per_run": runs, "paired": paired + versus}
    content["mask_actions"] = mask_actions
    content["episodes"] = episodes
    write_text(out / "results.json", json.dumps(content, indent=1))
    print(text)
    print(f"\nwritten: {out / 'results.md'}, {out / 'results.png'}, {out / 'results.json'}")


PROG = "evaluate_ego.py"
KEPT = "nothing written: the tables need every episode (fewer --scenes or --seeds run shorter)"

if __name__ == "__main__":
    with user_errors(PROG, debug_requested(sys.argv[1:]), kept=KEPT):  # Ctrl-C: one line
        main()
