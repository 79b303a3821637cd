"""Recovery windows: agents that drift off their log and return (ChauffeurNet-style)."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from policies.learned.data import WindowDataset
from policies.learned.parked import add_parked
from policies.learned.recovery import RecoveryConfig, perturb_tracks
from policies.learned.windows import WindowConfig, select_rows
from riskflow_env import dynamics
from riskflow_env.geometry import separation
from riskflow_env.scenarios import shipped_bank

CURRENT = 60  # a current step with history and future around it in the shipped scenes


@pytest.fixture(scope="module")
def scenes():
    """The shipped training bank's first highway, roundabout and u-turn scenes."""
    bank = shipped_bank("train")
    return [bank[0], bank[2], bank[6]]


def perturbed(scene, seed=0, **options):
    rows = select_rows(scene, CURRENT, WindowConfig())
    config = RecoveryConfig(copies=1, **({"share": 1.0} | options))
    tracks = perturb_tracks(
        scene.states, scene.valid, rows, CURRENT, scene.dt, config,
        np.random.default_rng(seed), DEFAULT.yaw_rate_max,
    )  # fmt: skip
    return rows, tracks


DEFAULT = dynamics.DEFAULT_CONFIG


def test_drift_is_bounded_starts_at_zero_and_mostly_returns(scenes):
    for scene in scenes:
        rows, tracks = perturbed(scene)
        drift = np.linalg.norm(tracks[rows, :, :2] - scene.states[rows, :, :2], axis=-1)
        moved = drift.max(axis=1) > 1e-9
        assert moved.sum() >= len(rows) // 3, scene.name
        assert np.all(drift[:, 0] == 0.0)  # the bump starts after the first step
        assert drift.max() < 1.5  # offset 1 m, plus the curve's share
        assert np.median(drift[moved, CURRENT]) > 0.1  # the current state is off the log
        left = drift[scene.valid[rows, -1], -1]
        assert left.max() < 0.5, scene.name  # back near the log after the bump


def test_a_unicycle_track_stays_a_unicycle_track(scenes):
    """Speeds and step lengths are the log's; each step follows the new heading."""
    for scene in scenes:
        rows, tracks = perturbed(scene)
        for row in rows:
            valid = scene.valid[row]
            if not valid.all():
                continue
            track = tracks[row]
            step = np.diff(track[:, :2], axis=0)
            direction = np.arctan2(step[:, 1], step[:, 0])
            moving = np.hypot(step[:, 0], step[:, 1]) > 0.05
            heading_error = dynamics.wrap_angle(direction - track[:-1, 3])[moving]
            assert np.abs(heading_error).max() < 1e-3, (scene.name, row)
            np.testing.assert_array_equal(track[:, 2], scene.states[row, :, 2])
            rates = dynamics.wrap_angle(np.diff(track[:, 3])) / scene.dt
            logged = dynamics.wrap_angle(np.diff(scene.states[row, :, 3])) / scene.dt
            assert np.all((np.abs(rates) <= DEFAULT.yaw_rate_max + 1e-5) | (rates == logged))


def test_standing_agents_and_zero_offset_stay_on_the_log(scenes):
    scene = scenes[0]
    states = scene.states.copy()
    states[1:3, :, 2] = 0.0  # two agents that do not move (their positions are not used)
    still = dataclasses.replace(scene, states=states)
    rows, tracks = perturbed(still)
    for row in (1, 2):
        if row in rows:
            np.testing.assert_array_equal(tracks[row], still.states[row])
    rows, tracks = perturbed(scene, offset=0.0)
    np.testing.assert_allclose(tracks[rows], scene.states[rows], atol=1e-9)


def test_draws_are_seeded(scenes):
    a = perturbed(scenes[1], seed=3)[1]
    b = perturbed(scenes[1], seed=3)[1]
    c = perturbed(scenes[1], seed=4)[1]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_dataset_adds_copies_with_their_own_cache(scenes, tmp_path):
    plain = WindowDataset(scenes[:2], stride=40, cache_path=tmp_path / "plain.npz")
    recovery = RecoveryConfig(copies=2)
    more = WindowDataset(scenes[:2], stride=40, cache_path=tmp_path / "more.npz", recovery=recovery)
    assert len(more) == 3 * len(plain)
    np.testing.assert_array_equal(more.index[::3], plain.index)
    original, copy = more.window(0), more.window(1)
    np.testing.assert_array_equal(original.history, plain.window(0).history)
    assert not np.array_equal(copy.history, original.history)
    np.testing.assert_array_equal(copy.agent_index, original.agent_index)
    again = WindowDataset(
        scenes[:2], stride=40, cache_path=tmp_path / "more.npz", recovery=recovery
    )
    np.testing.assert_array_equal(again.window(1).history, copy.history)
    with pytest.raises(TypeError, match="recovery must be a RecoveryConfig"):
        WindowDataset(scenes[:1], stride=40, recovery={"copies": 1})


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("copies", -1, "copies must be an int >= 0"),
        ("parked", 1.5, "parked must be an int, got 1.5"),
        ("share", 1.5, r"share must be in \[0, 1\]"),
        ("offset", float("nan"), "offset must be a number >= 0"),
        ("duration", (2.0, 1.0), "duration must be"),
    ],
)
def test_bad_options_name_the_field(field, value, match):
    with pytest.raises(ValueError, match=match):
        RecoveryConfig(**{field: value})


def assert_clear_of_every_track(scene, out, count):
    """The last ``count`` rows of ``out`` (parked) are 0.5 m clear of every logged box."""
    parked = out.states[-count:]
    gap = separation(
        parked[:, None, 0, None, :2], parked[:, None, 0, None, 3],
        out.length[-count:, None, None], out.width[-count:, None, None],
        scene.states[None, :, :, :2], scene.states[None, :, :, 3],
        scene.length[None, :, None], scene.width[None, :, None],
    )  # fmt: skip
    assert np.all((gap > 0.5) | ~scene.valid[None])


def test_parked_cars_stand_beside_the_road_clear_of_every_track(scenes):
    for seed, scene in enumerate(scenes):
        out = add_parked(scene, 3, CURRENT, np.random.default_rng(seed))
        count = out.states.shape[0] - scene.states.shape[0]
        assert count == 3, scene.name
        np.testing.assert_array_equal(out.states[:-count], scene.states)
        parked = out.states[-count:]
        assert np.all(parked == parked[:, :1]) and np.all(parked[..., 2] == 0.0)
        assert out.valid[-count:].all()
        assert np.all(np.asarray(scene.map.sdf_at(parked[:, 0, :2])) > out.width[-count:] / 2)
        assert_clear_of_every_track(scene, out, count)
    assert add_parked(scenes[0], 0, CURRENT, np.random.default_rng(0)) is scenes[0]


def test_turned_cars_keep_half_their_length_off_the_road_clear_of_every_track(scenes):
    """Cars parked across the road keep half their length (not their width) in the band
    of 0.3-3 m beyond the edge."""
    kept = 0
    for seed, scene in enumerate(scenes):
        out = add_parked(scene, 2, CURRENT, np.random.default_rng(seed), turn=1.0)
        count = out.states.shape[0] - scene.states.shape[0]
        kept += count
        if not count:
            continue
        parked = out.states[-count:]
        assert np.all(parked == parked[:, :1]) and np.all(parked[..., 2] == 0.0)
        half = out.length[-count:] / 2
        sdf = np.asarray(scene.map.sdf_at(parked[:, 0, :2]))
        assert np.all((sdf >= half + 0.3 - 1e-6) & (sdf <= half + 3.0 + 1e-6)), sdf
        assert_clear_of_every_track(scene, out, count)
    assert kept >= 2, "some road in the three scenes has room"


def test_the_recovery_cache_names_of_the_shipped_recipes_stay_the_same():
    """The window caches of the shipped recipes' recovery settings keep their file names
    (a hash of :meth:`RecoveryConfig.settings`) across versions."""

    def name(config):
        text = json.dumps(config.settings(), sort_keys=True).encode()
        return hashlib.sha256(text).hexdigest()[:12]

    assert name(RecoveryConfig(copies=1, parked=2)) == "72456277d5e0"
    shipped = RecoveryConfig(copies=1, parked=2, parked_turn=0.5, parked_jitter=0.3)
    assert name(shipped) == "1bd534b715f2"


def test_recovery_copies_with_parked_cars_show_them_standing(scenes):
    recovery = RecoveryConfig(copies=1, parked=2)
    data = WindowDataset(scenes[:1], stride=40, recovery=recovery)
    plain, copy = data.window(0), data.window(1)
    assert copy.agent_index.size == plain.agent_index.size + 2
    rows = copy.agent_index >= scenes[0].states.shape[0]
    assert rows.sum() == 2
    np.testing.assert_array_equal(copy.actions[rows], 0.0)
    np.testing.assert_array_equal(copy.future[rows, :, 2], 0.0)


def test_jittered_cars_creep_before_the_current_step_and_stand_after_it(scenes):
    scene = scenes[0]
    out = add_parked(scene, 3, CURRENT, np.random.default_rng(4), jitter=0.3)
    count = out.states.shape[0] - scene.states.shape[0]
    assert count == 3
    parked = out.states[-count:]
    pose = parked[:, CURRENT:][..., [0, 1, 3]]  # at its spot from the current step on
    assert np.all(pose == pose[:, :1]) and np.all(parked[:, CURRENT + 1 :, 2] == 0.0)
    history = parked[:, : CURRENT + 1]
    assert np.all(history[..., 2] >= 0.0) and history[..., 2].max() > 0.05
    assert np.all(history[..., 3] == history[:, :1, 3])  # the heading stays
    # each step moves along the heading, by at most the speed it reads
    steps = np.diff(history[..., :2], axis=1)
    direction = np.stack([np.cos(history[:, 0, 3]), np.sin(history[:, 0, 3])], axis=-1)
    along = np.einsum("ntk,nk->nt", steps, direction)
    np.testing.assert_allclose(np.abs(steps).sum(-1) > 0, np.abs(along) > 0)
    np.testing.assert_allclose(np.abs(along), history[:, 1:, 2] * scene.dt, atol=1e-6)
    # without the options nothing more is drawn: the cars of the plain call
    plain = add_parked(scene, 3, CURRENT, np.random.default_rng(4))
    np.testing.assert_array_equal(
        out.states[-count:, CURRENT, [0, 1, 3]], plain.states[-count:, 0, [0, 1, 3]]
    )
    np.testing.assert_array_equal(
        add_parked(scene, 3, CURRENT, np.random.default_rng(4), turn=0.0, jitter=0.0).states,
        plain.states,
    )


@pytest.mark.parametrize(
    ("options", "match"),
    [({"turn": 1.5}, r"turn must be a share in \[0, 1\]"), ({"jitter": -0.1}, "jitter must be")],
)
def test_bad_parked_looks_name_the_argument(scenes, options, match):
    with pytest.raises(ValueError, match=match):
        add_parked(scenes[0], 1, CURRENT, np.random.default_rng(0), **options)


def test_parked_looks_zero_keep_the_cache_settings_and_name_their_field():
    plain = RecoveryConfig(copies=1, parked=2)
    looks = RecoveryConfig(copies=1, parked=2, parked_turn=0.5, parked_jitter=0.3)
    assert plain.settings().keys().isdisjoint({"parked_turn", "parked_jitter"})
    assert looks.settings()["parked_turn"] == 0.5 and looks.settings()["parked_jitter"] == 0.3
    with pytest.raises(ValueError, match=r"parked_turn must be in \[0, 1\]"):
        RecoveryConfig(parked_turn=-0.1)
    with pytest.raises(ValueError, match="parked_jitter must be a number >= 0"):
        RecoveryConfig(parked_jitter=float("inf"))


def test_recovery_copies_with_jittered_parked_cars_stop_them(scenes):
    """A jittered parked car's reference actions bring it to rest and keep it there."""
    recovery = RecoveryConfig(copies=1, parked=2, parked_jitter=0.3)
    data = WindowDataset(scenes[:1], stride=40, recovery=recovery)
    copy = data.window(1)
    rows = copy.agent_index >= scenes[0].states.shape[0]
    assert rows.sum() == 2
    np.testing.assert_array_equal(copy.future[rows, :, 2], 0.0)
    assert np.all(copy.actions[rows, :, 0] <= 1e-6)  # braking or nothing, never speeding up
