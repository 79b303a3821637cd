"""Tests for riskflow_env.risk: hand-computed TTC cases, masking, frames, backends."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from riskflow_env.risk import (
    FEATURE_NAMES,
    MAX_INTERACTION_DISTANCE,
    NUM_PAIR_FEATURES,
    TAU_MAX,
    pair_risk,
    pairwise_features,
    risk_weight,
    time_to_collision,
)

L, W = 4.5, 2.0  # [m] default car box
F = {name: k for k, name in enumerate(FEATURE_NAMES)}


def scene(*agents, length=L, width=W):
    """agents: (x, y, v, psi) tuples -> state (A, 4), length (A,), width (A,)."""
    state = np.array(agents, dtype=np.float64)
    num = state.shape[0]
    return state, np.full(num, length, dtype=np.float64), np.full(num, width, dtype=np.float64)


def ttc_of(*agents, **sizes):
    return time_to_collision(*scene(*agents, **sizes))


def test_constants_and_names():
    assert TAU_MAX == 20.0
    assert MAX_INTERACTION_DISTANCE == 50.0
    assert NUM_PAIR_FEATURES == 8 == len(FEATURE_NAMES)


def test_head_on():
    # Same lane, 30 m apart, each at 10 m/s toward the other: gap 30 - 4.5, closing 20 m/s.
    ttc = ttc_of((0.0, 0.0, 10.0, 0.0), (30.0, 0.0, 10.0, math.pi))
    expected = (30.0 - L) / 20.0  # 1.275 s
    np.testing.assert_allclose(ttc[0, 1], expected, atol=1e-12)
    np.testing.assert_allclose(ttc[1, 0], expected, atol=1e-12)
    np.testing.assert_allclose(risk_weight(ttc)[0, 1], (TAU_MAX - expected) / TAU_MAX)


def test_following_faster_behind():
    # Follower at 20 m/s, leader 30 m ahead at 10 m/s: gap 25.5 m, dv 10 m/s.
    ttc = ttc_of((0.0, 0.0, 20.0, 0.0), (30.0, 0.0, 10.0, 0.0))
    np.testing.assert_allclose(ttc, [[0.0, 2.55], [2.55, 0.0]], atol=1e-12)


def test_following_slower_behind_is_safe():
    state, length, width = scene((0.0, 0.0, 10.0, 0.0), (30.0, 0.0, 20.0, 0.0))
    ttc = time_to_collision(state, length, width)
    np.testing.assert_allclose(ttc[0, 1], TAU_MAX)
    np.testing.assert_allclose(ttc[1, 0], TAU_MAX)
    np.testing.assert_allclose(pair_risk(state, length, width)[0], 0.0)


def test_crossing_takes_max_of_axes():
    # A drives +x from the origin; B drives +y from (20, -15). Boxes 4 x 2.
    # In A's frame: d = (20, -15), dv = (0, 10) - (10, 0) = (-10, 10), dpsi = 90 deg,
    # so B spans 2 m along x and 4 m along y: ext_x = (4 + 2)/2 = 3, ext_y = (2 + 4)/2 = 3.
    # t_x = (20 - 3) / 10 = 1.7 s, t_y = (15 - 3) / 10 = 1.2 s -> TTC = 1.7 s.
    a, b = (0.0, 0.0, 10.0, 0.0), (20.0, -15.0, 10.0, math.pi / 2)
    ttc = ttc_of(a, b, length=4.0, width=2.0)
    np.testing.assert_allclose(ttc[0, 1], 1.7, atol=1e-12)
    # In B's frame A sits at (15, 20) with dv = (-10, -10): t_x = 1.2, t_y = 1.7.
    np.testing.assert_allclose(ttc[1, 0], 1.7, atol=1e-12)
    # B already past A's lateral line and moving away along y: that axis never closes.
    ttc = ttc_of(a, (20.0, 15.0, 10.0, math.pi / 2), length=4.0, width=2.0)
    np.testing.assert_allclose(ttc[0, 1], TAU_MAX)


def test_diverging():
    state, length, width = scene((0.0, 0.0, 10.0, 0.0), (-20.0, 0.0, 10.0, math.pi))
    np.testing.assert_allclose(time_to_collision(state, length, width)[0, 1], TAU_MAX)
    np.testing.assert_allclose(pair_risk(state, length, width)[0], 0.0)


def test_overlapping_boxes():
    state, length, width = scene((0.0, 0.0, 10.0, 0.0), (2.0, 0.5, 3.0, 0.3))
    np.testing.assert_allclose(time_to_collision(state, length, width)[0, 1], 0.0)
    features, mask = pairwise_features(state, length, width)
    assert mask[0, 1] and mask[1, 0]
    np.testing.assert_allclose(features[0, 1, F["risk"]], 1.0)
    np.testing.assert_allclose(pair_risk(state, length, width)[0], [[0.0, 1.0], [1.0, 0.0]])


def test_lateral_neighbour_drifting_in():
    # B in the next lane (3.5 m to the left), same speed, heading 0.1 rad to the right.
    psi = -0.1
    state, length, width = scene((0.0, 0.0, 20.0, 0.0), (0.0, 3.5, 20.0, psi))
    dvy = 20.0 * math.sin(psi)  # -1.9967 m/s: B closes laterally at 1.9967 m/s
    ext_y = 0.5 * (W + abs(math.sin(psi)) * L + abs(math.cos(psi)) * W)
    expected = (3.5 - ext_y) / -dvy  # dx = 0 -> x gap closed, the y axis decides
    ttc = time_to_collision(state, length, width)
    np.testing.assert_allclose(ttc[0, 1], expected, atol=1e-12)
    # The same neighbour driving straight never closes.
    state[1, 3] = 0.0
    np.testing.assert_allclose(time_to_collision(state, length, width)[0, 1], TAU_MAX)


def test_features_by_hand():
    # A at the origin heading +y (90 deg); B 10 m ahead of A, heading +x.
    state, length, width = scene((0.0, 0.0, 5.0, math.pi / 2), (0.0, 10.0, 5.0, 0.0))
    features, mask = pairwise_features(state, length, width)
    e = features[0, 1]
    np.testing.assert_allclose(e[F["dx"]], 10.0, atol=1e-12)
    np.testing.assert_allclose(e[F["dy"]], 0.0, atol=1e-12)
    np.testing.assert_allclose(e[F["cos_dpsi"]], 0.0, atol=1e-12)
    np.testing.assert_allclose(e[F["sin_dpsi"]], -1.0, atol=1e-12)
    # World dv = (5, 0) - (0, 5) = (5, -5); rotated by -90 deg: (-5, -5).
    np.testing.assert_allclose(e[F["dvx"]], -5.0, atol=1e-12)
    np.testing.assert_allclose(e[F["dvy"]], -5.0, atol=1e-12)
    np.testing.assert_allclose(e[F["norm_distance"]], 10.0 / math.hypot(L, W), atol=1e-12)
    assert mask.tolist() == [[False, True], [True, False]]


def test_far_pairs_masked():
    agents = [(0.0, 0.0, 10.0, 0.0), (49.0, 0.0, 0.0, 0.0), (0.0, 50.5, 0.0, 0.0)]
    state, length, width = scene(*agents)
    features, mask = pairwise_features(state, length, width)
    assert mask[0, 1] and mask[1, 0]
    assert not mask[0, 2] and not mask[2, 0]  # 50.5 m apart
    assert not mask[1, 2]  # sqrt(49^2 + 50.5^2) m apart
    np.testing.assert_array_equal(features[~mask], 0.0)
    np.testing.assert_allclose(features[0, 1, F["dx"]], 49.0)


def test_invalid_agents_masked():
    agents = [(0.0, 0.0, 10.0, 0.0), (10.0, 0.0, 0.0, 0.0), (20.0, 0.0, 0.0, 0.0)]
    state, length, width = scene(*agents)
    valid = np.array([True, False, True])
    features, mask = pairwise_features(state, length, width, valid=valid)
    expected = np.array([[0, 0, 1], [0, 0, 0], [1, 0, 0]], dtype=bool)
    np.testing.assert_array_equal(mask, expected)
    np.testing.assert_array_equal(features[~mask], 0.0)
    risk = pair_risk(state, length, width, valid=valid)[0]
    assert risk[0, 2] > 0.0 and risk[0, 1] == 0.0


def random_scene(rng, num_agents=6, extent=30.0):
    state = np.stack(
        [
            rng.uniform(-extent, extent, num_agents),
            rng.uniform(-extent, extent, num_agents),
            rng.uniform(0.0, 25.0, num_agents),
            rng.uniform(-math.pi, math.pi, num_agents),
        ],
        axis=-1,
    )
    return state, rng.uniform(3.5, 6.0, num_agents), rng.uniform(1.6, 2.5, num_agents)


def test_frame_invariance():
    rng = np.random.default_rng(0)
    state, length, width = random_scene(rng)
    theta, shift = 1.234, np.array([117.0, -42.0])
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    moved = state.copy()
    moved[:, :2] = state[:, :2] @ rot.T + shift
    moved[:, 3] = state[:, 3] + theta
    f0, m0 = pairwise_features(state, length, width)
    f1, m1 = pairwise_features(moved, length, width)
    np.testing.assert_array_equal(m0, m1)
    np.testing.assert_allclose(f0, f1, atol=1e-9)


def test_symmetry_equal_boxes():
    rng = np.random.default_rng(1)
    # Opposite headings: the two frames differ by 180 deg, so e_ji's geometry equals e_ij's.
    state, length, width = scene((0.0, 0.0, 12.0, 0.4), (15.0, 6.0, 7.0, 0.4 + math.pi))
    f, _ = pairwise_features(state, length, width)
    np.testing.assert_allclose(f[0, 1], f[1, 0], atol=1e-12)
    # Same heading: positions and velocities flip sign, TTC is symmetric.
    for _ in range(20):
        state, length, width = random_scene(rng, num_agents=2)
        state[1, 3] = state[0, 3]
        length[:], width[:] = length[0], width[0]
        f, _ = pairwise_features(state, length, width)
        for name in ("dx", "dy", "dvx", "dvy"):
            np.testing.assert_allclose(f[0, 1, F[name]], -f[1, 0, F[name]], atol=1e-9)
        np.testing.assert_allclose(f[0, 1, F["risk"]], f[1, 0, F["risk"]], atol=1e-12)
    # Any headings: distance-like features are symmetric for any pair of boxes.
    state, length, width = random_scene(rng)
    f, m = pairwise_features(state, length, width)
    np.testing.assert_array_equal(m, m.T)
    np.testing.assert_allclose(f[..., F["norm_distance"]], f[..., F["norm_distance"]].T)
    np.testing.assert_allclose(f[..., F["cos_dpsi"]], f[..., F["cos_dpsi"]].T, atol=1e-12)
    np.testing.assert_allclose(f[..., F["sin_dpsi"]], -f[..., F["sin_dpsi"]].T, atol=1e-12)


def test_numpy_matches_torch():
    rng = np.random.default_rng(2)
    state, length, width = random_scene(rng, num_agents=8)
    valid = rng.uniform(size=8) > 0.2
    f_np, m_np = pairwise_features(state, length, width, valid)
    args = [torch.from_numpy(a) for a in (state, length, width, valid)]
    f_t, m_t = pairwise_features(*args)
    assert isinstance(f_t, torch.Tensor) and f_t.dtype == torch.float64
    np.testing.assert_allclose(f_t.numpy(), f_np, atol=1e-12)
    np.testing.assert_array_equal(m_t.numpy(), m_np)
    ttc_t = time_to_collision(*args[:3])
    np.testing.assert_allclose(ttc_t.numpy(), time_to_collision(state, length, width))


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_float32(backend):
    rng = np.random.default_rng(3)
    arrays = random_scene(rng)
    f64, _ = pairwise_features(*arrays)
    arrays32 = [a.astype(np.float32) for a in arrays]
    if backend == "torch":
        arrays32 = [torch.from_numpy(a) for a in arrays32]
    f32, _ = pairwise_features(*arrays32)
    ttc32 = time_to_collision(*arrays32)
    assert str(f32.dtype).endswith("float32") and str(ttc32.dtype).endswith("float32")
    f32 = f32.numpy() if backend == "torch" else f32
    np.testing.assert_allclose(f32, f64, rtol=1e-4, atol=1e-3)


def test_batch_dims_match_per_step():
    rng = np.random.default_rng(4)
    steps = [random_scene(rng, num_agents=5) for _ in range(4)]
    state, length, width = (np.stack(parts) for parts in zip(*steps, strict=True))
    valid = rng.uniform(size=(4, 5)) > 0.2
    features, mask = pairwise_features(state, length, width, valid)
    assert features.shape == (4, 5, 5, NUM_PAIR_FEATURES) and mask.shape == (4, 5, 5)
    for t in range(4):
        f_t, m_t = pairwise_features(state[t], length[t], width[t], valid[t])
        # Batched and per-step calls may vectorise reductions differently: float64 features
        # of order 1-100 agree to a few ulps, so 1e-12 absolute.
        np.testing.assert_allclose(features[t], f_t, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(mask[t], m_t)
    # Two leading dims (batch, time).
    f2, _ = pairwise_features(
        state[None].repeat(2, 0), length[None].repeat(2, 0), width[None].repeat(2, 0)
    )
    np.testing.assert_array_equal(f2[1], pairwise_features(state, length, width)[0])
    assert pair_risk(state, length, width, valid)[0].shape == (4, 5, 5)


def test_torch_gradients_finite_and_exact():
    # Head-on (dy = 0 -> sign 0), a parked car (zero closing speed), an overlapping pair,
    # an identical copy (distance 0 off the diagonal) and the diagonal itself.
    agents = [
        (0.0, 0.0, 10.0, 0.0),
        (30.0, 0.0, 10.0, math.pi),
        (0.0, 10.0, 0.0, 0.0),
        (1.0, 10.5, 0.0, 0.0),
        (1.0, 10.5, 0.0, 0.0),
    ]
    state, length, width = (torch.tensor(a, requires_grad=True) for a in scene(*agents))
    features, _ = pairwise_features(state, length, width)
    ttc = time_to_collision(state, length, width)
    (features.sum() + ttc.sum()).backward()
    for tensor in (state, length, width):
        assert torch.isfinite(tensor.grad).all()
    # Head-on TTC = (x_B - x_A - L) / (v_A + v_B): d TTC / d x_B = 1 / 20.
    (grad,) = torch.autograd.grad(time_to_collision(state, length, width)[0, 1], state)
    # (psi_B sits on the kink of |sin dpsi| at dpsi = pi: no unique derivative to check.)
    np.testing.assert_allclose(grad[1, :3].numpy(), [1 / 20, 0.0, -(30 - L) / 400], atol=1e-12)


def test_bad_shapes():
    state, length, width = scene((0.0, 0.0, 1.0, 0.0), (5.0, 0.0, 1.0, 0.0))
    with pytest.raises(ValueError, match="state"):
        time_to_collision(state[:, :3], length, width)
    with pytest.raises(ValueError, match="length"):
        pairwise_features(state, length[:1], width)
    with pytest.raises(ValueError, match="valid"):
        pairwise_features(state, length, width, valid=np.ones(3, dtype=bool))
