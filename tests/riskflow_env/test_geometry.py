"""Tests for riskflow_env.geometry: box corners, footprint, SAT overlap against shapely.

Float borderline cases: with random real-valued boxes, a pair at a distance (or
penetration depth) of ~1e-15 m can be decided either way by shapely and by the SAT
rounding. A random pair is called *borderline* when shapely's own verdict flips
after translating box b by ``EPS`` = 1e-9 m in one of 8 compass directions; such
pairs are excluded from the exact comparison (they are counted, and are rare).
Exact touching is covered separately with axis-aligned boxes whose coordinates are
exactly representable, where both sides compute without rounding.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch

from riskflow_env.geometry import (
    CENTRE,
    FOOTPRINT_NAMES,
    FRONT,
    LEFT,
    NUM_FOOTPRINT_POINTS,
    REAR,
    RIGHT,
    box_corners,
    footprint_points,
    pair_overlap,
    pairwise_overlap,
    separation,
    separation_gradient,
)

EPS = 1e-9  # [m] borderline margin for random pairs


def _polygons(xy, yaw, length, width):
    corners = box_corners(xy, yaw, length, width)
    return shapely.polygons(corners)


def _shapely_verdict(a, b, offset=(0.0, 0.0)):
    return shapely.intersects(a, shapely.transform(b, lambda c: c + np.asarray(offset)))


def _borderline(a, b):
    base = _shapely_verdict(a, b)
    flips = np.zeros_like(base)
    for angle in np.arange(8) * (math.pi / 4):
        offset = (EPS * math.cos(angle), EPS * math.sin(angle))
        flips |= _shapely_verdict(a, b, offset) != base
    return flips


def _random_boxes(rng, n, degenerate_fraction=0.0, spread=3.0):
    xy = rng.uniform(-spread, spread, (n, 2))
    yaw = rng.uniform(-math.pi, math.pi, n)
    length = rng.uniform(0.5, 6.0, n)
    width = rng.uniform(0.3, 3.0, n)
    if degenerate_fraction:
        kind = rng.integers(0, 3, n) * (rng.random(n) < degenerate_fraction)
        width = np.where(kind >= 1, 0.0, width)  # 1: segment
        length = np.where(kind == 2, 0.0, length)  # 2: point
    return xy, yaw, length, width


def _check_against_shapely(boxes_a, boxes_b, max_borderline_fraction=1e-3):
    expected = shapely.intersects(_polygons(*boxes_a), _polygons(*boxes_b))
    got = pair_overlap(*boxes_a, *boxes_b)
    border = _borderline(_polygons(*boxes_a), _polygons(*boxes_b))
    assert border.mean() <= max_borderline_fraction
    mismatch = (got != expected) & ~border
    assert not mismatch.any(), np.flatnonzero(mismatch)[:10]
    return expected


# --- corners and footprint ------------------------------------------------------


def test_corners_axis_aligned_order():
    corners = box_corners(np.array([1.0, 2.0]), np.array(0.0), np.array(4.0), np.array(2.0))
    expected = [[3.0, 1.0], [3.0, 3.0], [-1.0, 3.0], [-1.0, 1.0]]  # FR, FL, RL, RR
    np.testing.assert_array_equal(corners, expected)


def test_corners_rotate_with_yaw():
    rng = np.random.default_rng(0)
    xy, yaw, length, width = _random_boxes(rng, 200)
    corners = box_corners(xy, yaw, length, width)
    base = box_corners(np.zeros_like(xy), np.zeros_like(yaw), length, width)  # (n, 4, 2)
    rotation = np.stack(
        [np.stack([np.cos(yaw), -np.sin(yaw)], -1), np.stack([np.sin(yaw), np.cos(yaw)], -1)], -2
    )
    expected = np.einsum("nij,nkj->nki", rotation, base) + xy[:, None, :]
    np.testing.assert_allclose(corners, expected, atol=1e-12)


def test_corners_counter_clockwise_area():
    rng = np.random.default_rng(1)
    xy, yaw, length, width = _random_boxes(rng, 500)
    x, y = box_corners(xy, yaw, length, width)[..., 0], box_corners(xy, yaw, length, width)[..., 1]
    area = 0.5 * np.sum(x * np.roll(y, -1, -1) - np.roll(x, -1, -1) * y, axis=-1)
    np.testing.assert_allclose(area, length * width, rtol=1e-12)


def test_footprint_midpoints_and_centre():
    rng = np.random.default_rng(2)
    xy, yaw, length, width = _random_boxes(rng, 300)
    points = footprint_points(xy, yaw, length, width)
    assert points.shape == (300, NUM_FOOTPRINT_POINTS, 2) and len(FOOTPRINT_NAMES) == 9
    np.testing.assert_array_equal(points[:, :4], box_corners(xy, yaw, length, width))
    corners = points[:, :4]
    for mid, (i, j) in zip(
        (FRONT, LEFT, REAR, RIGHT), ((0, 1), (1, 2), (2, 3), (3, 0)), strict=True
    ):
        np.testing.assert_allclose(
            points[:, mid], 0.5 * (corners[:, i] + corners[:, j]), atol=1e-12
        )
    np.testing.assert_allclose(points[:, CENTRE], xy, atol=1e-12)
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    np.testing.assert_allclose(points[:, FRONT] - xy, 0.5 * length[:, None] * heading, atol=1e-12)


def test_footprint_broadcasts_scalars_and_batches():
    xy = np.zeros((3, 5, 2))
    points = footprint_points(xy, np.zeros((3, 5)), 4.0, 2.0)
    assert points.shape == (3, 5, 9, 2)
    np.testing.assert_array_equal(points[1, 2, LEFT], [0.0, 1.0])


def test_footprint_of_one_state_read_from_an_array():
    """A heading read out of a state array is a numpy scalar, not an array: accepted."""
    states = np.array([[1.0, 2.0, 5.0, 0.3]])
    one = footprint_points(states[0, :2], states[0, 3], 4.0, 2.0)
    np.testing.assert_array_equal(one, footprint_points(states[0, :2], states[0, 3:4], 4.0, 2.0)[0])
    assert box_corners(states[0, :2], states[0, 3], np.float64(4.0), 2.0).shape == (4, 2)


# --- overlap against shapely ----------------------------------------------------


def test_random_pairs_match_shapely():
    rng = np.random.default_rng(3)
    expected = _check_against_shapely(_random_boxes(rng, 5000), _random_boxes(rng, 5000))
    assert 0.2 < expected.mean() < 0.8  # both outcomes well represented


def test_random_degenerate_pairs_match_shapely():
    rng = np.random.default_rng(4)
    boxes_a = _random_boxes(rng, 4000, degenerate_fraction=0.7)
    boxes_b = _random_boxes(rng, 4000, degenerate_fraction=0.7)
    expected = _check_against_shapely(boxes_a, boxes_b, max_borderline_fraction=5e-3)
    assert expected.any() and not expected.all()


def _near_touching(rng, n, gap):
    """Box b whose corner is ``gap`` [m] outside (or inside, gap < 0) an edge of box a."""
    xy_a, yaw_a, length_a, width_a = _random_boxes(rng, n)
    _, yaw_b, length_b, width_b = _random_boxes(rng, n)
    edge = rng.integers(0, 4, n)  # 0 front, 1 left, 2 rear, 3 right
    normal_angle = yaw_a + edge * (math.pi / 2)
    normal = np.stack([np.cos(normal_angle), np.sin(normal_angle)], -1)
    tangent = np.stack([-normal[:, 1], normal[:, 0]], -1)
    half_depth = np.where(edge % 2 == 0, length_a, width_a)[:, None] / 2
    half_span = np.where(edge % 2 == 0, width_a, length_a)[:, None] / 2
    along = rng.uniform(-0.8, 0.8, (n, 1)) * half_span  # contact away from a's corners
    contact = xy_a + half_depth * normal + along * tangent
    offsets = box_corners(np.zeros((n, 2)), yaw_b, length_b, width_b)  # (n, 4, 2)
    support = offsets[np.arange(n), np.argmin(np.einsum("nkj,nj->nk", offsets, normal), -1)]
    xy_b = contact - support + gap[:, None] * normal
    return (xy_a, yaw_a, length_a, width_a), (xy_b, yaw_b, length_b, width_b)


def test_rotated_near_touching_match_shapely():
    rng = np.random.default_rng(5)
    n = 4000
    gap = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(-7, -2, n)
    boxes_a, boxes_b = _near_touching(rng, n, gap)
    expected = _check_against_shapely(boxes_a, boxes_b, max_borderline_fraction=0.0)
    np.testing.assert_array_equal(expected, gap < 0)
    # A corner at distance gap from a face: the SAT separation is that distance.
    sep = separation(*boxes_a, *boxes_b)
    np.testing.assert_allclose(sep[gap > 0], gap[gap > 0], rtol=1e-6, atol=1e-12)


def test_separation_bounds_shapely_distance():
    rng = np.random.default_rng(6)
    boxes_a, boxes_b = _random_boxes(rng, 3000), _random_boxes(rng, 3000)
    sep = separation(*boxes_a, *boxes_b)
    distance = shapely.distance(_polygons(*boxes_a), _polygons(*boxes_b))
    apart = sep > 0
    assert np.all(sep[apart] <= distance[apart] + 1e-12)
    assert np.all(distance[apart] <= math.sqrt(2) * sep[apart] + 1e-12)
    np.testing.assert_array_equal(distance[~apart], 0.0)


def _aligned(x, y, length, width):
    arr = np.asarray
    return arr([x, y], dtype=float), arr(0.0), arr(float(length)), arr(float(width))


EXACT_CASES = {
    # name: (box a, box b) with yaw 0 and dyadic coordinates: no rounding anywhere
    "edge_to_edge": (_aligned(0, 0, 4, 2), _aligned(4, 0.5, 4, 2)),
    "edge_to_edge_side": (_aligned(0, 0, 4, 2), _aligned(1.25, 2, 4, 2)),
    "corner_to_corner": (_aligned(0, 0, 4, 2), _aligned(4, 2, 4, 2)),
    "corner_to_corner_mixed": (_aligned(0, 0, 4, 2), _aligned(-2.5, -1.75, 1, 1.5)),
    "gap_x": (_aligned(0, 0, 4, 2), _aligned(4.25, 0, 4, 2)),
    "gap_diagonal": (_aligned(0, 0, 4, 2), _aligned(4.125, 2.125, 4, 2)),
    "nested": (_aligned(0, 0, 4, 2), _aligned(0.5, 0.25, 1, 0.5)),
    "identical": (_aligned(1, -1, 4.5, 1.75), _aligned(1, -1, 4.5, 1.75)),
    "far_apart": (_aligned(0, 0, 4, 2), _aligned(1000, -500, 4, 2)),
    "segment_on_edge": (_aligned(0, 0, 4, 2), _aligned(0, 1, 2, 0)),
    "segment_off_edge": (_aligned(0, 0, 4, 2), _aligned(0, 1.125, 2, 0)),
    "segment_crossing": (_aligned(0, 0, 4, 2), _aligned(0, 0, 8, 0)),
    "segment_end_touch": (_aligned(0, 0, 4, 2), _aligned(3, 0, 2, 0)),
    "segments_collinear_touch": (_aligned(0, 0, 4, 0), _aligned(4, 0, 4, 0)),
    "segments_parallel": (_aligned(0, 0, 4, 0), _aligned(0, 0.5, 4, 0)),
    "point_on_corner": (_aligned(0, 0, 4, 2), _aligned(2, 1, 0, 0)),
    "point_inside": (_aligned(0, 0, 4, 2), _aligned(0.5, 0.5, 0, 0)),
    "point_outside": (_aligned(0, 0, 4, 2), _aligned(2.25, 0, 0, 0)),
    "point_on_segment": (_aligned(0, 0, 4, 0), _aligned(1, 0, 0, 0)),
    "points_equal": (_aligned(1, 2, 0, 0), _aligned(1, 2, 0, 0)),
    "points_apart": (_aligned(1, 2, 0, 0), _aligned(1, 2.5, 0, 0)),
}


@pytest.mark.parametrize("name", sorted(EXACT_CASES))
def test_exact_cases_match_shapely(name):
    box_a, box_b = EXACT_CASES[name]
    expected = shapely.intersects(_polygons(*box_a), _polygons(*box_b))
    for a, b in ((box_a, box_b), (box_b, box_a)):
        assert bool(pair_overlap(*a, *b)) == bool(expected)
    if name.startswith(("edge_to_edge", "corner_to_corner")):  # touching, no overlap area
        assert shapely.area(shapely.intersection(_polygons(*box_a), _polygons(*box_b))) == 0
        assert separation(*box_a, *box_b) == 0.0 and separation(*box_b, *box_a) == 0.0


def test_exact_cases_cover_both_outcomes():
    verdicts = [bool(pair_overlap(*a, *b)) for a, b in EXACT_CASES.values()]
    assert any(verdicts) and not all(verdicts)


def test_tolerance_semantics():
    box_a = _aligned(0, 0, 4, 2)
    near = _aligned(4.25, 2.25, 4, 2)  # corner gap 0.25 on both axes, distance 0.25*sqrt(2)
    assert not pair_overlap(*box_a, *near)
    assert pair_overlap(*box_a, *near, tolerance=0.25)
    assert not pair_overlap(*box_a, *near, tolerance=0.125)
    deep = _aligned(3.5, 0, 4, 2)  # penetration depth 0.5
    assert pair_overlap(*box_a, *deep, tolerance=-0.5)
    assert not pair_overlap(*box_a, *deep, tolerance=-0.625)
    assert separation(*box_a, *deep) == -0.5


# --- pairwise -------------------------------------------------------------------


def _scene(rng, shape):
    xy = rng.uniform(-15.0, 15.0, (*shape, 2))
    yaw = rng.uniform(-math.pi, math.pi, shape)
    length = rng.uniform(3.5, 5.5, shape)
    width = rng.uniform(1.6, 2.2, shape)
    return xy, yaw, length, width


def test_pairwise_symmetric_diagonal_false_and_matches_pairs():
    rng = np.random.default_rng(7)
    xy, yaw, length, width = _scene(rng, (32,))
    xy[1] = xy[0]  # guarantee an overlap
    overlap = pairwise_overlap(xy, yaw, length, width)
    assert overlap.shape == (32, 32) and overlap.dtype == bool
    np.testing.assert_array_equal(overlap, overlap.T)
    assert not overlap.diagonal().any() and overlap[0, 1]
    i, j = np.triu_indices(32, 1)
    polys = _polygons(xy, yaw, length, width)
    np.testing.assert_array_equal(overlap[i, j], shapely.intersects(polys[i], polys[j]))


def test_pairwise_valid_mask():
    xy = np.zeros((4, 2))  # all agents on top of each other
    valid = np.array([True, False, True, True])
    overlap = pairwise_overlap(xy, np.zeros(4), np.full(4, 4.0), np.full(4, 2.0), valid=valid)
    expected = np.outer(valid, valid) & ~np.eye(4, dtype=bool)
    np.testing.assert_array_equal(overlap, expected)


def test_pairwise_batch_over_time_and_scalar_dims():
    rng = np.random.default_rng(8)
    xy, yaw, length, width = _scene(rng, (6, 16))
    valid = rng.random((6, 16)) < 0.8
    batched = pairwise_overlap(xy, yaw, length[0], width[0], valid=valid)  # dims (A,)
    assert batched.shape == (6, 16, 16) and batched.any()
    for t in range(6):
        single = pairwise_overlap(xy[t], yaw[t], length[0], width[0], valid=valid[t])
        np.testing.assert_array_equal(batched[t], single)
    scalar = pairwise_overlap(xy, yaw, 4.5, 1.8)
    np.testing.assert_array_equal(scalar, pairwise_overlap(xy, yaw, np.full(16, 4.5), 1.8))


def test_torch_matches_numpy():
    rng = np.random.default_rng(9)
    xy, yaw, length, width = _scene(rng, (3, 24))
    valid = rng.random((3, 24)) < 0.9
    expected = pairwise_overlap(xy, yaw, length, width, valid=valid)
    tensors = [torch.from_numpy(a) for a in (xy, yaw, length, width, valid)]
    got = pairwise_overlap(*tensors[:4], valid=tensors[4])
    assert isinstance(got, torch.Tensor) and got.dtype == torch.bool
    np.testing.assert_array_equal(got.numpy(), expected)
    np.testing.assert_allclose(
        footprint_points(*tensors[:4]).numpy(), footprint_points(xy, yaw, length, width)
    )


def test_torch_separation_differentiable():
    xy = torch.tensor([[0.0, 0.0], [4.5, 0.0]], dtype=torch.float64, requires_grad=True)
    yaw = torch.zeros(2, dtype=torch.float64)
    sep = separation(xy[0], yaw[0], 4.0, 2.0, xy[1], yaw[1], 4.0, 2.0)
    sep.backward()
    assert sep.item() == pytest.approx(0.5)
    np.testing.assert_allclose(xy.grad.numpy(), [[-1.0, 0.0], [1.0, 0.0]])


@pytest.mark.parametrize("degenerate_fraction", [0.0, 0.3])
def test_separation_gradient_is_autograds_and_numpy_is_torch(degenerate_fraction):
    """The closed-form derivatives of ``separation`` against autograd (float64, random
    pairs, degenerate boxes included); the separation itself is ``separation``'s bit for
    bit, and numpy gives what torch does (to rounding: their sines differ in the last bit)."""
    rng = np.random.default_rng(11)
    boxes_a = _random_boxes(rng, 3000, degenerate_fraction)
    boxes_b = _random_boxes(rng, 3000, degenerate_fraction)
    gap, d_xy, d_yaw_a, d_yaw_b = separation_gradient(*boxes_a, *boxes_b)
    tensors = [torch.from_numpy(x) for x in (*boxes_a, *boxes_b)]
    for index in (0, 1, 4, 5):
        tensors[index].requires_grad_(True)
    reference = separation(*tensors)
    reference.sum().backward()
    np.testing.assert_array_equal(gap, separation(*boxes_a, *boxes_b))
    np.testing.assert_allclose(gap, reference.detach().numpy(), atol=1e-12)  # numpy, torch
    np.testing.assert_allclose(d_xy, tensors[4].grad.numpy(), atol=1e-12)
    np.testing.assert_allclose(-d_xy, tensors[0].grad.numpy(), atol=1e-12)
    np.testing.assert_allclose(d_yaw_a, tensors[1].grad.numpy(), atol=1e-12)
    np.testing.assert_allclose(d_yaw_b, tensors[5].grad.numpy(), atol=1e-12)
    torch_result = separation_gradient(*[t.detach() for t in tensors])
    for ours, theirs in zip(torch_result, (gap, d_xy, d_yaw_a, d_yaw_b), strict=True):
        np.testing.assert_allclose(ours.numpy(), theirs, rtol=1e-12, atol=1e-12)
