"""DiffusionAdversary closed loop, and ``riskflow-train --generator diffusion`` end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from policies.baselines.diffusion.model import DiffusionDenoiser, load_diffusion
from policies.baselines.diffusion.policy import PHASES, DiffusionAdversary
from policies.baselines.diffusion.sampling import reverse_chain
from policies.learned.checkpoint import load_generator
from policies.learned.generator import CheckpointError
from policies.learned.sampler import decode_plans
from policies.learned.window_types import collate_windows
from policies.learned.windows import window_from_view
from policies.train import GENERATOR, METRICS_LOG
from policies.train import main as train_main
from riskflow_env.dynamics import DEFAULT_CONFIG
from riskflow_env.view import ScenePolicy
from tests.policies.highway_banks import write_banks
from tests.policies.straight_road import (
    TINY_MODEL,
    TINY_NORMALIZER,
    perturbed_generator,
    road_env,
    run_closed_loop,
)

TINY = TINY_MODEL
NORMALIZER = TINY_NORMALIZER


@pytest.fixture(scope="module")
def denoiser() -> DiffusionDenoiser:
    return DiffusionDenoiser(perturbed_generator(0))


def adversary(denoiser, **kwargs) -> DiffusionAdversary:
    kwargs = {"k": 2, "sampling_steps": 5, "seed": 3, **kwargs}
    return DiffusionAdversary(denoiser=denoiser, normalizer=NORMALIZER, **kwargs)


def run(policy, steps: int):
    """Closed loop on the road with the ego holding speed, every action within bounds."""

    def check(view, policy, actions):
        assert set(actions) == set(view.live_agents) - {"ego"}
        for action in actions.values():
            assert DEFAULT_CONFIG.accel_min <= action[0] <= DEFAULT_CONFIG.accel_max
            assert abs(action[1]) <= DEFAULT_CONFIG.yaw_rate_max

    return run_closed_loop(policy, steps, hook=check)


@pytest.mark.parametrize("variant", ["ctg", "ctgpp", "ccdiff"])
def test_closed_loop_runs_replans_and_repeats_with_the_seed(denoiser, variant):
    policy = adversary(denoiser, variant=variant)
    assert isinstance(policy, ScenePolicy)
    _, first = run(policy, 7)
    assert policy.cycles == 2 and set(policy.timings) == {*PHASES, "total"}
    assert policy.controllable.sum() == 2 and not policy.controllable[0]
    assert policy.guidance_losses.shape[1] == 2
    _, second = run(adversary(denoiser, variant=variant), 7)
    for a, b in zip(first, second, strict=True):
        assert a.keys() == b.keys() and all(np.array_equal(a[n], b[n]) for n in a)
    _, other = run(adversary(denoiser, variant=variant, seed=4), 7)
    assert any(not np.array_equal(other[0][n], first[0][n]) for n in first[0])


def test_k0_is_the_unguided_chain_and_guidance_touches_only_a_c(denoiser):
    env = road_env()
    unguided = adversary(denoiser, k=0)
    unguided.reset(env.view())
    unguided.plan(env.view())
    assert not unguided.controllable.any()
    np.testing.assert_array_equal(unguided.plans, unguided.base_plans)
    # The plans are the reverse chain of the cycle's noise (kept in policy.noise).
    window = window_from_view(env.view(), unguided.window_config)
    scene = denoiser.encode(collate_windows([window]))
    x0 = reverse_chain(denoiser, scene, unguided.noise[:, None], unguided.levels)[-1]
    actions, _ = decode_plans(x0[0], scene.state[0], scene.agent_mask[0], NORMALIZER)
    # The policy's chain and this one are different code paths (batch layout, op order) in
    # float32: actions of a few m/s^2 carry rounding of about 8 * 2**-24 = 5e-7 per op,
    # and 100 denoising steps compound it (1.2e-6 seen on another machine), so 1e-5.
    np.testing.assert_allclose(
        unguided.plan_actions[window.agent_index], actions.numpy(), rtol=0, atol=1e-5
    )

    guided = adversary(denoiser, k=2, step_size=0.3)
    guided.reset(env.view())
    guided.plan(env.view())
    np.testing.assert_array_equal(guided.base_plans, unguided.plans)
    same = guided.plan_mask & ~guided.controllable
    np.testing.assert_array_equal(guided.plans[same], unguided.plans[same])
    moved = guided.controllable
    assert moved.sum() == 2
    assert not np.allclose(guided.plans[moved], unguided.plans[moved])


def test_unanchored_guidance_runs_one_chain(denoiser):
    policy = adversary(denoiser, variant="ctgpp", anchor=False)
    policy.stitch_steps = 0  # the second cycle's plans as planned (no blend with the first)
    run(policy, 6)
    assert policy.cycles == 2 and policy.controllable.sum() == 2
    np.testing.assert_array_equal(policy.plans, policy.base_plans)
    assert policy.timings["denoising"] < policy.timings["guidance"]


def test_draw_and_bad_options(denoiser):
    class Renderer:
        def __init__(self):
            self.overlays = {}

        def set_overlay(self, name, *args, **kwargs):
            self.overlays[name] = args

    policy = adversary(denoiser)
    run(policy, 1)
    renderer = Renderer()
    policy.draw(renderer)
    assert set(renderer.overlays) == {"diffusion_base", "diffusion_guided"}
    for kwargs, match in (
        ({"variant": "ctg+"}, "variant"),
        ({"k": -1}, "k must be"),
        ({"eta": 2.0}, "eta"),
        ({"inner_steps": 2, "variant": "ctgpp"}, "inner_steps"),
        ({"sampling_steps": 101}, "sampling_steps"),
    ):
        with pytest.raises(ValueError, match=match):
            adversary(denoiser, **kwargs)
    assert adversary(denoiser, guidance_horizon=7).guidance.horizon == 7
    with pytest.raises(ValueError, match="normalizer"):
        DiffusionAdversary(denoiser=denoiser)


@pytest.fixture(scope="module")
def banks(tmp_path_factory):
    root = tmp_path_factory.mktemp("banks")
    return write_banks((root / "train", root / "val"), ([0, 2], [4]))


def train_args(banks, out, *extra: str) -> list[str]:
    """A fast ``riskflow-train`` command line: tiny model, stride 16, batches of 2."""
    return [
        "--data", str(banks[0]), "--val-data", str(banks[1]), "--out", str(out),
        "--model", json.dumps(TINY.to_dict()), "--stride", "16", "--batch-size", "2",
        "--eval-every", "3", "--log-every", "1", "--val-windows", "2", "--num-samples", "2",
        *extra,
    ]  # fmt: skip


def test_riskflow_train_generator_diffusion_end_to_end(banks, tmp_path, refused):
    out = tmp_path / "diffusion"
    diffusion = ("--generator", "diffusion", "--diffusion-steps", "20", "--val-sampling-steps", "3")
    assert train_main(train_args(banks, out, "--steps", "3", *diffusion)) == 0
    final = json.loads((out / METRICS_LOG).read_text().splitlines()[-1])
    assert final["step"] == 3 and np.isfinite(final["val_ade"]) and "train_eps_mse" in final
    denoiser, normalizer, metadata = load_diffusion(out / GENERATOR)
    assert denoiser.diffusion.num_steps == 20 and denoiser.diffusion.prediction == "v"
    assert denoiser.config == TINY and metadata["step"] == 3
    run(DiffusionAdversary(denoiser=denoiser, normalizer=normalizer, sampling_steps=3), 2)
    with refused("trained --generator diffusion"):
        train_main(train_args(banks, out, "--steps", "4", "--resume"))
    meanflow = tmp_path / "meanflow"
    train_main(train_args(banks, meanflow, "--steps", "1"))
    with pytest.raises(CheckpointError, match="not a diffusion checkpoint"):
        load_diffusion(meanflow / GENERATOR)
    assert load_generator(meanflow / GENERATOR)[0].config == TINY
