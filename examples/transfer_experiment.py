"""Does training against the adversary transfer? PPO egos trained against three kinds of
traffic, each evaluated in ordinary traffic and under attack, on shipped and recorded scenes.

    python examples/transfer_experiment.py --out runs/transfer --seeds 1,2 \\
        --data ../shared/data/scenarionet

For every seed of ``--seeds`` it trains the target-ego recipe of docs/tutorials/rl-ego.md
(``train_ego_ppo.py`` with the sampling MPC's maneuvers, the batched vector env, 80,000
decisions) three times, with the same budget and seed and only the traffic changed:

* ``adversary``: the RiskFlow adversary, K ramped from 1 to 5, target ``ego`` (the recipe);
* ``unguided``: the unguided generator (K = 0), the same learned traffic without attacks;
* ``idm``: IDM traffic.

A run folder that has a final model is reused, one with checkpoints is resumed
(``train_ego_ppo.py --resume``), so the command picks up where an interrupted one stopped;
both load model files from ``--out`` and so need ``--trust-model``. Then every trained
ego drives the same episodes, choosing the most probable maneuver among those its action
mask allows (``--no-mask-actions``: the raw policy's choice):

* the shipped evaluation bank (``--scenes`` scenes x ``--eval-seeds``), in the unguided
  generator's traffic and under the adversary (K = 5, target ``ego``);
* with ``--data`` (a ScenarioNet folder or a folder of ``.npz`` scenes: recorded driving),
  the same scenes' log replay, the unguided generator and the adversary.

Each ego's evaluation is saved with its settings and its episodes' outcomes, each keyed
by (scene, traffic seed), in ``<out>/episodes/<trained against>-seed<N>.json``, and not
re-run while the settings are the same. The report, ``<out>/transfer.md`` (printed) and
``<out>/transfer.json``, has per evaluation traffic and per trained-against traffic the
ego collision rate and off-road rate (Wilson 95% intervals, pooled over seeds) and the
progress [m], then the adversary-trained ego's paired difference in collision rate
against each of the two others on the same episodes (interval and exact two-sided McNemar
test, :func:`policies.statistics.paired_difference`). The question it answers: does the
adversary-trained ego collide less than the others under attack, and how much more or
less in ordinary traffic?

``--train-args`` adds options to every training command (e.g. a smaller budget:
``--train-args "--total-timesteps 20000"``; the tests run the whole pipeline on a tiny
one); the options that make the three egos differ (``--traffic``, ``--k-start``,
``--k-end``) and ``--seed`` / ``--out`` are the experiment's, not its.
"""

from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from evaluate_ego import ppo_factory, run_options, spread_scenes
from tqdm import tqdm

from policies.cli_inputs import open_data, parse_seeds
from policies.dataclass_cli import check_at_least, parse_dataclass, passed_options
from policies.rl.adversary import AdversaryStage, ScenePolicyConfig
from policies.rl.evaluation import evaluate
from policies.rl.paired import outcome_counts
from policies.rl.report import markdown_table
from policies.rl.runs import run_begun
from policies.statistics import mean_summary, paired_difference, rate
from policies.stress.summary import progress
from riskflow_env.atomic_files import write_text
from riskflow_env.cli_errors import user_errors
from riskflow_env.config import EnvConfig
from riskflow_env.folder_lock import check_output_folder
from riskflow_env.scenarios import shipped_bank

HERE = Path(__file__).resolve().parent
STOPS = (signal.SIGINT, signal.SIGTERM)  # the training process stops on them, saving
RECIPE = (
    "--vec-env", "batched", "--num-envs", "16", "--n-steps", "64", "--maneuver-set", "mpc",
    "--target-start", "ego", "--target-end", "ego", "--checkpoint-every", "10000",
)  # fmt: skip
TRAINED_AGAINST = {  # name: what train_ego_ppo.py is given besides the recipe
    "adversary": (),
    "unguided": ("--k-start", "0", "--k-end", "0"),
    "idm": ("--traffic", "idm"),
}
EXPERIMENT_OPTIONS = ("--traffic", "--k-start", "--k-end", "--seed", "--out", "--resume")
ATTACK = ScenePolicyConfig(stage=AdversaryStage(k=5, target="ego"))
TRAFFICS = {  # evaluation traffic: (scene source, traffic)
    "generator": ("shipped", ScenePolicyConfig(stage=AdversaryStage(k=0))),
    "adversary": ("shipped", ATTACK),
    "replay (data)": ("data", ScenePolicyConfig(kind="replay")),
    "generator (data)": ("data", ScenePolicyConfig(stage=AdversaryStage(k=0))),
    "adversary (data)": ("data", ATTACK),
}


@dataclass(frozen=True)
class Options:
    """Options of transfer_experiment.py."""

    out: Path = Path("runs/transfer")
    """the experiment's folder: runs, per-episode outcomes and the report"""
    seeds: str = "1,2"
    """training seeds (each trains three egos)"""
    data: str | None = None
    """recorded scenes to evaluate on too: a ScenarioNet folder or a folder of .npz scenes"""
    scenes: int = 35
    """shipped evaluation scenes, spread evenly over the bank"""
    data_scenes: int = 100
    """at most this many scenes of --data"""
    eval_seeds: str = "0,1,2"
    """traffic seeds of the evaluation episodes (every ego drives the same ones)"""
    episode_steps: int = 100
    """evaluation episode length [steps of 0.1 s]"""
    train_args: str = ""
    """options appended to every train_ego_ppo.py command (they override the recipe's)"""
    mask_actions: bool = True
    """the egos choose among the maneuvers their action mask allows (--no-mask-actions: the
    raw policies)"""
    trust_model: bool = False
    """load (reuse or resume) the runs found in --out (SB3 model files are pickles that can
    run code: only for files you trust, docs/reference/security.md); the runs this command
    trains from the start need no flag"""

    def __post_init__(self) -> None:
        for name in ("seeds", "eval_seeds"):
            parse_seeds(getattr(self, name), "--" + name.replace("_", "-"))
        check_at_least(self, dict.fromkeys(("scenes", "data_scenes", "episode_steps"), 1))
        check_output_folder(self.out, "--out")
        why = "the experiment sets them"
        passed_options(self.train_args, "--train-args", EXPERIMENT_OPTIONS, why)


def train(options: Options, name: str, seed: int) -> Path:
    """The run folder of the ego trained against ``name`` with ``seed``: trained here, or
    resumed or reused (which needs ``--trust-model``)."""
    run = options.out / name / f"seed{seed}"
    final = run / "final_model.zip"
    started = run_begun(run)  # a checkpoint or the final model
    if started and not options.trust_model:
        _fail(
            f"{run} has {'a trained model' if final.is_file() else 'checkpoints'}: add "
            "--trust-model to load its model files (pickles that can run code; "
            "docs/reference/security.md)"
        )
    if final.is_file():
        return run
    script = str(HERE / "train_ego_ppo.py")
    if started:
        command = [sys.executable, script, "--resume", str(run)]
    else:
        extra = (*shlex.split(options.train_args), *TRAINED_AGAINST[name])
        command = [sys.executable, script, *RECIPE, *extra, "--seed", str(seed), "--out", str(run)]
    print("$ " + shlex.join(command), flush=True)
    status = run_training(command)
    if status in (128 + signal.SIGINT, 128 + signal.SIGTERM):
        print(f"transfer_experiment.py: interrupted; {run} keeps its checkpoint: run the same "
              "command again to resume", file=sys.stderr)  # fmt: skip
        sys.exit(status)
    if status != 0 or not final.is_file():
        _fail(f"training {run} failed (status {status}, its error above)")
    return run


def run_training(command: list[str]) -> int:
    """Run ``command`` and return its exit status. Ctrl-C (a terminal signals the whole
    process group) and a job's SIGTERM reach the training process itself, which saves a
    checkpoint and stops; this process waits for it instead of dying first."""
    previous = {signum: signal.signal(signum, signal.SIG_IGN) for signum in STOPS}
    try:
        return subprocess.run(command).returncode
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _fail(message: str) -> None:
    print(f"transfer_experiment.py: error: {message}", file=sys.stderr)
    sys.exit(2)


def settings(options: Options, scenes: dict) -> dict:
    """What an ego's evaluation depends on besides its model (an evaluation saved with
    other settings is run again)."""
    return {
        "scenes": {source: [scene.name for scene in chosen] for source, chosen in scenes.items()},
        "eval_seeds": list(parse_seeds(options.eval_seeds)),
        "episode_steps": options.episode_steps,
        "mask_actions": options.mask_actions,
    }


def outcomes(options: Options, name: str, run: Path, scenes: dict) -> dict[str, list]:
    """``{evaluation traffic: [[scene, traffic seed, collided, off-road, progress], ...]}``
    of the trained ego of ``run`` on every episode (read from its file when an earlier call
    wrote it with the same settings)."""
    path = options.out / "episodes" / f"{name}-{run.name}.json"
    wanted = settings(options, scenes)
    if path.is_file():
        saved = json.loads(path.read_text())
        if saved.get("settings") == wanted:
            return saved["episodes"]
        print(f"{path}: saved with other settings: evaluating again")
    _, interface = run_options(run)
    factory = ppo_factory(run / "final_model.zip", interface, options.mask_actions)
    config = EnvConfig(episode_steps=options.episode_steps)
    seeds = wanted["eval_seeds"]
    labels = [label for label, (source, _) in TRAFFICS.items() if scenes[source]]
    total = len(seeds) * sum(len(scenes[TRAFFICS[label][0]]) for label in labels)
    result = {}
    with tqdm(total=total, desc=f"{name} {run.name}", unit="episode") as bar:
        for label in labels:
            source, traffic = TRAFFICS[label]
            records = evaluate(
                {name: factory}, [traffic], scenes[source], seeds, config, lambda _: bar.update()
            )
            keys = [(seed, scene.name) for seed in seeds for scene in scenes[source]]
            result[label] = [  # evaluate's order: seed after seed, every scene
                [scene, seed, bool(r.metrics["ego_collided"]), bool(r.metrics["ego_offroad"]),
                 progress(r)]
                for (seed, scene), r in zip(keys, records[name, traffic.label], strict=True)
            ]  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, json.dumps({"settings": wanted, "episodes": result}))
    return result


def report(results: dict[str, dict[str, list]]) -> tuple[str, dict]:
    """The Markdown table and its JSON of ``{trained against: {traffic: episodes}}`` (the
    episodes of every training seed, concatenated); ValueError if two egos' episodes of a
    traffic are not the same (scene, seed) list."""
    rows, summaries = [], {}
    pairs, pair_lines = [], _header(
        "evaluated in", "adversary-trained minus", "collision rate difference [95%]",
        "p (McNemar)", "episodes",
    )  # fmt: skip
    for traffic in TRAFFICS:
        keys = {n: [tuple(e[:2]) for e in r[traffic]] for n, r in results.items() if traffic in r}
        if len({tuple(k) for k in keys.values()}) > 1:
            raise ValueError(f"{traffic}: the egos' episodes differ; cannot pair them")
        episodes = {n: np.array([e[2:] for e in results[n][traffic]], float) for n in keys}
        for name, values in episodes.items():
            entry = {
                "traffic": traffic,
                "trained_against": name,
                "ego_collision_rate": rate(int(values[:, 0].sum()), len(values)),
                "ego_offroad_rate": rate(int(values[:, 1].sum()), len(values)),
                "progress": mean_summary(values[:, 2].tolist()),
            }
            rows.append(entry)
            summaries[f"trained against {name}", traffic] = entry
        if "adversary" not in episodes:
            continue
        ours = episodes["adversary"][:, 0].astype(bool)
        for name, values in episodes.items():
            if name == "adversary":
                continue
            # paired_difference's names: "trained" is the adversary-trained ego
            diff = paired_difference(outcome_counts(ours, values[:, 0].astype(bool)))
            pairs.append({
                "traffic": traffic, "against": name, "n": diff["n"],
                "adversary_trained": diff["trained"], "other": diff["untrained"],
                "adversary_trained_only": diff["trained_only"],
                "other_only": diff["untrained_only"],
                **{k: diff[k] for k in ("difference", "low", "high", "p_value")},
            })  # fmt: skip
            pair_lines.append(
                f"| {traffic} | {name} | {diff['difference']:+.3f} "
                f"[{diff['low']:+.3f}, {diff['high']:+.3f}] | {diff['p_value']:.3g} | {len(ours)} |"
            )
    table = markdown_table(summaries, ("ego_collision_rate", "ego_offroad_rate", "progress"))
    text = table + "\n\nPaired, same episodes:\n\n" + "\n".join(pair_lines)
    return text, {"rows": rows, "paired": pairs}


def _header(*names: str) -> list[str]:
    return ["| " + " | ".join(names) + " |", "|" + " --- |" * len(names)]


def main(argv: list[str] | None = None) -> None:
    description = " ".join(__doc__.split("\n\n")[0].split())
    options = parse_dataclass(Options, argv, prog="transfer_experiment.py", description=description)
    kept = "the trained egos and saved evaluations in --out are kept: the same command resumes"
    with user_errors("transfer_experiment.py", kept=kept):
        experiment(options)


def experiment(options: Options) -> None:
    """Train (or reuse) every ego, evaluate each, write and print the report."""
    try:
        data = open_data(options.data) if options.data is not None else []
    except ValueError as error:
        _fail(str(error))
    scenes = {
        "shipped": spread_scenes(shipped_bank("eval"), options.scenes),
        "data": [data[i] for i in range(min(options.data_scenes, len(data)))],
    }
    runs = {(name, seed): train(options, name, seed)
            for seed in parse_seeds(options.seeds) for name in TRAINED_AGAINST}  # fmt: skip
    results: dict[str, dict[str, list]] = {}
    for (name, _), run in runs.items():  # seeds in order: episodes line up across egos
        for traffic, episodes in outcomes(options, name, run, scenes).items():
            results.setdefault(name, {}).setdefault(traffic, []).extend(episodes)
    text, content = report(results)
    write_text(options.out / "transfer.md", text + "\n")
    write_text(options.out / "transfer.json", json.dumps(content, indent=1))
    print(text)
    print(f"\nwritten: {options.out / 'transfer.md'}, {options.out / 'transfer.json'}")


if __name__ == "__main__":
    main()
