"""Oriented vehicle boxes: corners, footprint samples and box-box overlap.

A vehicle is a closed rectangle given by its centre ``xy`` (..., 2) [m], heading
``yaw`` (...) [rad], ``length`` (...) [m] along the heading and ``width`` (...) [m]
across it. Leading dimensions broadcast, so the same call serves one step
``(A,)``, a rollout ``(T, A)`` or a batch ``(B, T, A)``. Zero length or width is
allowed: the box degenerates to a segment or a point and every function still
holds.

Overlap uses the separating axis theorem (SAT) on the four box axes (heading and
its normal for each box). For rectangles, including degenerate ones, these axes
are complete: two boxes are disjoint iff their projections are disjoint on one
of them. Everything is written once against the array API (numpy or torch).
"""

from __future__ import annotations

import math

from riskflow_env._array import Array, asarray_like, device, namespace

FOOTPRINT_NAMES = (
    "front_right",
    "front_left",
    "rear_left",
    "rear_right",
    "front",
    "left",
    "rear",
    "right",
    "centre",
)
NUM_FOOTPRINT_POINTS = 9
FRONT_RIGHT, FRONT_LEFT, REAR_LEFT, REAR_RIGHT = 0, 1, 2, 3
FRONT, LEFT, REAR, RIGHT, CENTRE = 4, 5, 6, 7, 8
CORNERS = slice(0, 4)  # index of the 4 corners in the footprint

# Footprint point k sits at (_ALONG[k] * length/2, _ACROSS[k] * width/2) in the
# vehicle frame (x forward, y to the left).
_ALONG = (1.0, 1.0, -1.0, -1.0, 1.0, 0.0, -1.0, 0.0, 0.0)
_ACROSS = (-1.0, 1.0, 1.0, -1.0, 0.0, 1.0, 0.0, -1.0, 0.0)


def to_frame(dx: Array, dy: Array, cos: Array, sin: Array) -> tuple[Array, Array]:
    """World offsets ``(dx, dy)`` [m] into a frame of heading ``psi`` given as
    ``cos psi``, ``sin psi``: ``(forward, left)`` [m] (x ahead, y to the left).

    Every frame change of the project goes through this pair (vehicle frames, the ego's
    scene frame, pair frames); they take ``cos`` and ``sin`` so that a caller computes
    them once for many offsets. numpy or torch, any broadcastable shapes.
    """
    return cos * dx + sin * dy, -sin * dx + cos * dy


def from_frame(forward: Array, left: Array, cos: Array, sin: Array) -> tuple[Array, Array]:
    """The inverse of :func:`to_frame`: offsets in a frame of heading ``psi`` back to
    world offsets ``(dx, dy)`` [m]."""
    return cos * forward - sin * left, sin * forward + cos * left


def footprint_points(xy: Array, yaw: Array, length: Array, width: Array) -> Array:
    """Samples of a vehicle's footprint in world coordinates.

    Args:
        xy: (..., 2) box centres [m].
        yaw: (...) headings [rad], counter-clockwise from the world x axis.
        length: (...) box lengths along the heading [m] (array or float).
        width: (...) box widths across the heading [m] (array or float).

    Returns:
        (..., 9, 2) points [m] in ``FOOTPRINT_NAMES`` order: the 4 corners
        counter-clockwise from front-right (FR, FL, RL, RR), the 4 edge midpoints
        (front, left, rear, right), then the centre.
    """
    xp = namespace(xy, yaw, length, width)
    along = 0.5 * asarray_like(length, yaw)[..., None] * asarray_like(_ALONG, xy)  # (..., 9)
    across = 0.5 * asarray_like(width, yaw)[..., None] * asarray_like(_ACROSS, xy)
    cos, sin = xp.cos(yaw)[..., None], xp.sin(yaw)[..., None]
    x = xy[..., 0:1] + along * cos - across * sin
    y = xy[..., 1:2] + along * sin + across * cos
    return xp.stack((x, y), axis=-1)


def box_corners(xy: Array, yaw: Array, length: Array, width: Array) -> Array:
    """Corners of oriented boxes.

    Args: as ``footprint_points``.

    Returns:
        (..., 4, 2) corners [m], counter-clockwise from front-right: FR, FL, RL, RR
        (so the shoelace area is ``+length * width``).
    """
    return footprint_points(xy, yaw, length, width)[..., CORNERS, :]


def separation(
    xy_a: Array,
    yaw_a: Array,
    length_a: Array,
    width_a: Array,
    xy_b: Array,
    yaw_b: Array,
    length_b: Array,
    width_b: Array,
) -> Array:
    """Largest gap between the projections of box a and box b on the 4 SAT axes.

    On each axis k (heading and normal of a, heading and normal of b) the gap is
    ``|(c_b - c_a) . k| - r_a(k) - r_b(k)``, with r the box's projected half-extent.
    The result is the maximum over the 4 axes:

    * ``> 0``: disjoint. It is a lower bound on the Euclidean distance d between
      the boxes, and at least d / sqrt(2).
    * ``<= 0``: the closed boxes intersect (``0`` exactly when they touch). Then
      ``-separation`` is the penetration depth: the shortest translation of one
      box that makes them only touch.

    Args:
        xy_a: (..., 2) centres of boxes a [m].
        yaw_a: (...) headings of a [rad].
        length_a: (...) lengths of a [m] (array or float).
        width_a: (...) widths of a [m] (array or float).
        xy_b, yaw_b, length_b, width_b: the same for boxes b; all broadcast.

    Returns:
        (...) signed separation [m], same dtype as the inputs. Symmetric in a, b
        bit for bit. Differentiable almost everywhere under torch.
    """
    return _Gaps(xy_a, yaw_a, length_a, width_a, xy_b, yaw_b, length_b, width_b).largest()


def separation_gradient(
    xy_a: Array,
    yaw_a: Array,
    length_a: Array,
    width_a: Array,
    xy_b: Array,
    yaw_b: Array,
    length_b: Array,
    width_b: Array,
) -> tuple[Array, Array, Array, Array]:
    """``separation`` and its derivatives in closed form (arguments as ``separation``).

    The derivative of the largest gap (the first of the four in ``separation``'s order
    where several are equal; ``|x|`` has derivative 0 at 0, as under autograd): a gap
    depends on the centres through ``c_b - c_a`` only, so the derivative with respect to
    ``xy_a`` is minus that with respect to ``xy_b``. Autograd through ``separation``
    builds a graph of ~150 operations per call; the avoidance steps of the learned
    scene policies take this gradient many times per planning cycle.

    Returns:
        ``(separation, d_xy_b, d_yaw_a, d_yaw_b)``: ``(...)``, ``(..., 2)``, ``(...)``,
        ``(...)``; ``d_xy_a = -d_xy_b``. The separation is ``separation``'s, bit for bit.
    """
    terms = _Gaps(xy_a, yaw_a, length_a, width_a, xy_b, yaw_b, length_b, width_b)
    xp, gaps = terms.xp, terms.gaps
    best = terms.largest()
    cos_a, sin_a, cos_b, sin_b = terms.cos_a, terms.sin_a, terms.cos_b, terms.sin_b
    p0, p1, p2, p3 = terms.projections
    s0, s1, s2, s3 = (xp.sign(p) for p in terms.projections)
    # d|cos_ab| / d yaw_a = -d/d yaw_b and d|sin_ab| / d yaw_b = -d/d yaw_a
    c_turn = xp.sign(terms.cos_ab) * terms.sin_ab
    s_turn = xp.sign(terms.sin_ab) * terms.cos_ab
    half_len_a, half_wid_a = 0.5 * length_a, 0.5 * width_a
    half_len_b, half_wid_b = 0.5 * length_b, 0.5 * width_b
    turn_b = half_len_b * c_turn - half_wid_b * s_turn  # the size terms' d/d yaw_b
    cross_b = half_len_b * s_turn - half_wid_b * c_turn
    turn_a = half_len_a * c_turn - half_wid_a * s_turn
    cross_a = half_len_a * s_turn - half_wid_a * c_turn
    per_gap = (  # (d/d dx, d/d dy, d/d yaw_a, d/d yaw_b) of each gap
        (s0 * cos_a, s0 * sin_a, s0 * p1 - turn_b, turn_b),
        (-s1 * sin_a, s1 * cos_a, -s1 * p0 + cross_b, -cross_b),
        (s2 * cos_b, s2 * sin_b, -turn_a, s2 * p3 + turn_a),
        (-s3 * sin_b, s3 * cos_b, cross_a, -s3 * p2 - cross_a),
    )
    chosen = per_gap[3]
    for gap, derivatives in zip(gaps[2::-1], per_gap[2::-1], strict=True):  # first largest wins
        pick = gap == best
        chosen = tuple(xp.where(pick, d, c) for d, c in zip(derivatives, chosen, strict=True))
    d_x, d_y, d_yaw_a, d_yaw_b = chosen
    return best, xp.stack((d_x, d_y), axis=-1), d_yaw_a, d_yaw_b


class _Gaps:
    """The four SAT gaps of a pair of boxes and the terms their derivatives use (one
    implementation for ``separation`` and ``separation_gradient``)."""

    def __init__(self, xy_a, yaw_a, length_a, width_a, xy_b, yaw_b, length_b, width_b):
        xp = self.xp = namespace(xy_a, yaw_a, xy_b, yaw_b)
        cos_a, sin_a = self.cos_a, self.sin_a = xp.cos(yaw_a), xp.sin(yaw_a)
        cos_b, sin_b = self.cos_b, self.sin_b = xp.cos(yaw_b), xp.sin(yaw_b)
        dx = xy_b[..., 0] - xy_a[..., 0]
        dy = xy_b[..., 1] - xy_a[..., 1]
        half_len_a, half_wid_a = 0.5 * length_a, 0.5 * width_a
        half_len_b, half_wid_b = 0.5 * length_b, 0.5 * width_b
        # |heading_a . heading_b| = |normal_a . normal_b| and |heading_a . normal_b| =
        # |normal_a . heading_b|: two numbers describe the relative orientation.
        self.cos_ab = cos_a * cos_b + sin_a * sin_b  # cos(yaw_b - yaw_a)
        self.sin_ab = cos_a * sin_b - sin_a * cos_b  # sin(yaw_b - yaw_a)
        cos_ab, sin_ab = xp.abs(self.cos_ab), xp.abs(self.sin_ab)
        # the centre offset along heading_a, normal_a, heading_b, normal_b
        self.projections = (
            dx * cos_a + dy * sin_a,
            dy * cos_a - dx * sin_a,
            dx * cos_b + dy * sin_b,
            dy * cos_b - dx * sin_b,
        )
        p0, p1, p2, p3 = (xp.abs(p) for p in self.projections)
        self.gaps = (
            p0 - half_len_a - (half_len_b * cos_ab + half_wid_b * sin_ab),
            p1 - half_wid_a - (half_len_b * sin_ab + half_wid_b * cos_ab),
            p2 - half_len_b - (half_len_a * cos_ab + half_wid_a * sin_ab),
            p3 - half_wid_b - (half_len_a * sin_ab + half_wid_a * cos_ab),
        )

    def largest(self) -> Array:
        """The largest of the four gaps: the separation."""
        xp, gaps = self.xp, self.gaps
        return xp.maximum(xp.maximum(gaps[0], gaps[1]), xp.maximum(gaps[2], gaps[3]))


def pair_overlap(
    xy_a: Array,
    yaw_a: Array,
    length_a: Array,
    width_a: Array,
    xy_b: Array,
    yaw_b: Array,
    length_b: Array,
    width_b: Array,
    tolerance: float = 0.0,
) -> Array:
    """Elementwise overlap of box a with box b (arguments as ``separation``).

    A pair overlaps when ``separation <= tolerance``, i.e. when on every one of the
    4 SAT axes the gap between the projections is at most ``tolerance`` [m].

    * ``tolerance = 0``: exact intersection of closed boxes; touching counts
      (shapely ``intersects``).
    * ``tolerance > 0``: also near misses. Every pair closer than ``tolerance``
      overlaps, and no pair farther than ``sqrt(2) * tolerance`` does.
    * ``tolerance < 0``: only pairs whose penetration depth is at least
      ``-tolerance`` overlap.

    Returns:
        (...) bool.
    """
    args = (xy_a, yaw_a, length_a, width_a, xy_b, yaw_b, length_b, width_b)
    return separation(*args) <= tolerance


def pairwise_overlap(
    xy: Array,
    yaw: Array,
    length: Array,
    width: Array,
    valid: Array | None = None,
    tolerance: float = 0.0,
) -> Array:
    """Overlap of every pair among A agents, vectorised (no loop over pairs).

    Args:
        xy: (..., A, 2) box centres [m].
        yaw: (..., A) headings [rad].
        length: (..., A) lengths [m] (array or float).
        width: (..., A) widths [m] (array or float).
        valid: optional (..., A) bool; pairs involving an invalid agent are False.
        tolerance: overlap threshold [m] on the SAT separation, see ``pair_overlap``.

    Returns:
        (..., A, A) bool, symmetric, with a False diagonal. Entry [i, j] is True
        when agents i and j (both valid) overlap.
    """
    xp = namespace(xy, yaw, length, width)
    x, y, yaw, length, width = xp.broadcast_arrays(
        xy[..., 0], xy[..., 1], yaw, asarray_like(length, yaw), asarray_like(width, yaw)
    )
    # Bounding-circle prefilter: boxes whose centres are farther apart than the sum of
    # their circumradii (plus sqrt(2) * tolerance, see ``pair_overlap``) cannot overlap,
    # so the SAT test runs only on the few candidate pairs. The slack keeps the
    # prefilter conservative under rounding; the verdicts are those of ``pair_overlap``.
    radius = 0.5 * xp.sqrt(length**2 + width**2)
    reach = radius[..., :, None] + radius[..., None, :] + math.sqrt(2.0) * max(tolerance, 0.0)
    dx, dy = x[..., None, :] - x[..., :, None], y[..., None, :] - y[..., :, None]
    candidate = dx * dx + dy * dy <= reach * reach * (1.0 + 1e-9) + 1e-9
    num_agents = x.shape[-1]
    candidate = candidate & ~xp.eye(num_agents, dtype=xp.bool, device=device(x))
    if valid is not None:
        candidate = candidate & valid[..., :, None] & valid[..., None, :]
    index = xp.nonzero(candidate)  # (..., i, j) index arrays of the candidate pairs
    overlap = xp.zeros(candidate.shape, dtype=xp.bool, device=device(x))
    if index[0].shape[0] == 0:
        return overlap
    first, second = (*index[:-1],), (*index[:-2], index[-1])  # (..., i) and (..., j)

    def box(at: tuple) -> tuple[Array, Array, Array, Array]:
        return xp.stack([x[at], y[at]], axis=-1), yaw[at], length[at], width[at]

    overlap[index] = pair_overlap(*box(first), *box(second), tolerance)
    return overlap
