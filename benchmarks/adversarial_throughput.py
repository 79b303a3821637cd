"""Planning throughput of the K = 5 adversary: B scenes per call vs B one-scene calls.

The ``--method`` adversary (default ``riskflow``, built by
:func:`policies.registry.build_policy` with the library's defaults: the realistic base;
``riskflow-raw`` is the raw generator) plans the first B shipped evaluation scenes
(``shipped_bank("eval")``, each reset in its own env) in two ways, measured in one run:

* **batched**: :class:`policies.pipeline.batched.BatchedAdversary` plans all B
  scenes in one call (one encoder pass, one generator pass, one guidance loop);
* **one at a time**: B policy copies each planning its own scene (``plan``, the
  one-scene path).

Both run the method's stages (docs/explanation/architecture.md; ``riskflow``: window and
encoder, TTC ranking, MeanFlow pass, stitching, avoidance steps, the guidance steps on the
top-``--k`` vehicles, emit, holding at rest) on the same views. Reported per B:
planning calls per second, scenes planned per second and the ratio of the batched
scenes/s to the loop's. Rounds are interleaved (batched, then loop, per B) and the best
round of each is reported (the least disturbed one on a shared machine).

``--method strive`` measures STRIVE-style the same way (its latent optimisation batched
over the scenes' rows: one generator forward and backward pass per step for all B), and
``--method ctg`` (``ctgpp``, ``ccdiff``) the diffusion baselines (one base chain and one
guided chain for all B scenes; ``--diffusion-steps`` levels, DDIM below the model's 100).

    python benchmarks/adversarial_throughput.py [--scenes 1 8 32] [--rounds 3] [--device cpu]
    python benchmarks/adversarial_throughput.py --device cuda --loop-device cpu  # GPU vs CPU
    python benchmarks/adversarial_throughput.py --method riskflow-raw
    python benchmarks/adversarial_throughput.py --method strive --scenes 1 8
    python benchmarks/adversarial_throughput.py --method ctg --diffusion-steps 10
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from methods import make_policy
from tqdm import tqdm

import riskflow_env
from policies.cli_inputs import check_device
from policies.dataclass_cli import check_at_least, check_sizes, parse_dataclass
from policies.pipeline.batched import BatchedAdversary
from policies.registry import DIFFUSION_STEPS_OPTION, METHODS, method_spec
from riskflow_env.cli_errors import run_script
from riskflow_env.processes import MAX_THREADS
from riskflow_env.scenarios import shipped_bank
from riskflow_env.view import SceneView


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    scenes: tuple[int, ...] = (1, 8, 32)
    """scenes per planning call (B)"""
    method: str = "riskflow"
    """an adversary of riskflow-eval --list: 'riskflow' (output-space guidance),
    'riskflow-raw' (on the raw generator), 'strive' (STRIVE-style latent optimisation), a
    diffusion baseline ('ctg', 'ctgpp', 'ccdiff'), ..."""
    k: int = 5
    """size of the controllable set A_c in each scene"""
    guidance_steps: int | None = None
    """K_g guidance steps per cycle (riskflow, strive); default: the method's"""
    diffusion_steps: int | None = None
    """denoising levels of the diffusion baselines: None for all (DDPM), fewer for DDIM"""
    rounds: int = 3
    """interleaved timed rounds per B; the best is reported"""
    calls: int = 3
    """planning calls of all B scenes per round (each way)"""
    threads: int = 1
    """torch CPU threads while planning one scene at a time"""
    batched_threads: int | None = None
    """torch CPU threads while planning B scenes per call (None: --threads); large batches
    are big tensor ops, which more threads can share"""
    device: str = "cpu"
    """torch device (cuda where a GPU is present)"""
    loop_device: str | None = None
    """torch device of the one-scene-at-a-time loop (None: --device); today's loop runs on
    cpu, so ``--device cuda --loop-device cpu`` compares batched GPU planning with it"""

    def __post_init__(self) -> None:
        lows = {"k": 0, "guidance_steps": 0, "diffusion_steps": 1, "rounds": 1, "calls": 1,
                "threads": 1, "batched_threads": 1}  # fmt: skip
        optional = ("guidance_steps", "diffusion_steps", "batched_threads")
        highs = {"threads": MAX_THREADS, "batched_threads": MAX_THREADS}
        check_at_least(self, lows, optional, highs=highs)
        check_sizes(self, ("scenes",))
        check_device(self.device)
        if self.loop_device is not None:
            check_device(self.loop_device, "--loop-device")


# the adversaries: methods with a controllable set (the reference traffic and the unguided
# generators have none)
ADVERSARIES = tuple(name for name, spec in METHODS.items() if spec.uses_k)


def build(options: Options, device: str, threads: int, like=None):
    """The ``--method`` adversary on ``device``; ``like``: a policy whose model it shares."""
    spec, extra = method_spec(options.method), {"threads": threads}
    if spec.diffusion:
        if options.diffusion_steps is not None:
            extra[DIFFUSION_STEPS_OPTION] = options.diffusion_steps
        if like is not None:
            extra |= {"denoiser": like.denoiser, "normalizer": like.normalizer}
    else:
        if options.guidance_steps is not None:
            extra["guidance_steps"] = options.guidance_steps
        if like is not None:
            extra |= {"generator": like.model, "normalizer": like.normalizer}
    return make_policy(options.method, extra, k=options.k, device=device)


def _parse(argv: list[str] | None = None) -> Options:
    return parse_dataclass(
        Options,
        argv,
        prog="adversarial_throughput.py",
        description=__doc__.split("\n")[0],
        debug=True,
    )


def evaluation_views(count: int) -> list[SceneView]:
    """The first views of the first ``count`` shipped evaluation scenes, an env each."""
    bank = shipped_bank("eval")
    if count > len(bank):
        raise SystemExit(f"--scenes asks for {count} scenes; the evaluation bank has {len(bank)}")
    views = []
    for index in range(count):
        scenario = bank[index]
        env = riskflow_env.parallel_env(scenarios=scenario)
        env.reset(seed=0, options={"scenario": scenario})
        views.append(env.view())
    return views


def time_calls(plan, calls: int) -> float:
    """Seconds per call of ``plan()`` (``calls`` calls)."""
    start = time.perf_counter()
    for _ in range(calls):
        plan()
    return (time.perf_counter() - start) / calls


def measure(policy, batched, views: list[SceneView], options: Options) -> dict:
    """Best seconds per planning call of all scenes, batched (copies of ``batched``) and
    one at a time (copies of ``policy``)."""
    batch = BatchedAdversary(batched, len(views))
    batch.reset(views)
    alone = [policy.spawn(policy.seed + index) for index in range(len(views))]
    for copy, view in zip(alone, views, strict=True):
        copy.reset(view)

    def loop() -> None:
        for copy, view in zip(alone, views, strict=True):
            copy.plan(view)

    batch.plan(views)  # warm-up (and the map stack)
    loop()
    best = {"batched": float("inf"), "loop": float("inf")}
    for _ in range(options.rounds):
        best["batched"] = min(best["batched"], time_calls(lambda: batch.plan(views), options.calls))
        best["loop"] = min(best["loop"], time_calls(loop, options.calls))
    best["phases"] = batch.scenes[0].timings
    best["loop_phases"] = {
        name: sum(copy.timings[name] for copy in alone) for name in best["phases"]
    }
    return best


def main(argv: list[str] | None = None) -> list[dict]:
    """Print the tables; returns their rows (``scenes``, ``batched`` and ``loop`` [s per
    planning of all B scenes], ``phases`` of the last batched call and ``loop_phases``
    summed over the last loop's calls [s])."""
    options = _parse(argv)
    if options.method not in ADVERSARIES:
        raise SystemExit(f"--method must be one of {list(ADVERSARIES)}, got {options.method!r}")
    loop_device = options.loop_device or options.device
    policy = build(options, loop_device, options.threads)
    batched_threads = options.batched_threads or options.threads
    same_device = loop_device == options.device
    # the same model (the same checkpoint), B scenes per call
    batched = build(options, options.device, batched_threads, like=policy if same_device else None)
    views = evaluation_views(max(options.scenes))
    agents = [int(v.present.sum()) for v in views]
    if method_spec(options.method).diffusion:
        planning = f"{options.diffusion_steps or 'all'} denoising levels"
    else:
        planning = f"K_g = {options.guidance_steps or 'the default'}"
    print(
        f"{options.method} ({type(policy).__name__}), K = {options.k}, {planning}, shipped "
        f"checkpoint, device {options.device} (loop: {loop_device}), CPU threads: "
        f"{options.threads} one at a time, {batched_threads} batched; shipped "
        f"evaluation scenes 0..{len(views) - 1} ({min(agents)}-{max(agents)} vehicles, mean "
        f"{np.mean(agents):.1f}); best of {options.rounds} rounds of {options.calls} calls\n"
    )
    header = (
        f"{'B':>4}{'batched calls/s':>17}{'batched scenes/s':>18}"
        f"{'loop calls/s':>14}{'loop scenes/s':>15}{'ratio':>8}"
    )
    print(header)
    rows = []
    for count in tqdm(options.scenes, "scene counts", leave=False):  # stderr
        best = measure(policy, batched, views[:count], options)
        rows.append({"scenes": count, **best})
        batched_rate, loop_rate = 1.0 / best["batched"], 1.0 / best["loop"]
        ratio = best["loop"] / best["batched"]
        print(
            f"{count:>4}{batched_rate:>17.2f}{batched_rate * count:>18.1f}"
            f"{loop_rate * count:>14.1f}{loop_rate * count:>15.1f}{ratio:>7.2f}x"
        )
    print(
        "\nloop calls/s counts one-scene calls (= its scenes/s); ratio = batched scenes/s / "
        "loop scenes/s"
    )
    print("\nphases [ms] of the last batched call, and summed over the last loop's B calls:")
    names = [name for name in rows[0]["phases"] if name != "total"] + ["total"]
    print(f"{'B':>4}{'':>8}" + "".join(f"{name:>11}" for name in names))
    for row in rows:
        for label, key in (("batched", "phases"), ("loop", "loop_phases")):
            timings = row[key]
            cells = "".join(f"{1e3 * timings[name]:>11.1f}" for name in names)
            print(f"{row['scenes']:>4}{label:>8}{cells}")
    return rows


if __name__ == "__main__":
    run_script("adversarial_throughput.py", main)
