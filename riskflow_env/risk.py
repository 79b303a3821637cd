"""Time-to-collision (TTC) risk and pairwise interaction features ``e_ij``.

Implements docs/explanation/architecture.md (the RiskFlow paper's TTC risk weighting). Everything
is a pure function written once against the array API, so the same code serves numpy
(env observations) and torch (policy encoder features, differentiable). All ordered
pairs ``(i, j)`` are computed at once by broadcasting; any leading dims (time, batch)
are carried through.

Conventions: agent state ``(..., A, 4) = (x [m], y [m], v [m/s], psi [rad])``, velocity
``v * (cos psi, sin psi)``; box sizes ``length, width: (..., A) [m]``. A pair quantity
``out[..., i, j]`` describes agent ``j`` as seen from agent ``i``, in ``i``'s frame
(x forward along ``psi_i``, y to the left).

TTC of the pair (i, j), per axis ``k`` of i's frame (``d_k`` the relative position of j,
``dv_k`` the relative velocity of j w.r.t. i, ``dpsi = psi_j - psi_i``)::

    ext_x = (L_i + |cos dpsi| L_j + |sin dpsi| W_j) / 2      # j's box projected on i's axes
    ext_y = (W_i + |sin dpsi| L_j + |cos dpsi| W_j) / 2
    gap_k = |d_k| - ext_k                                    # [m]
    c_k   = -sign(d_k) * dv_k                                # closing speed [m/s]
    t_k   = 0 if gap_k <= 0 else gap_k / c_k if c_k > 0 else tau_max
    TTC   = clip(max(t_x, t_y), 0, tau_max)                  # [s]
    risk  = (tau_max - clip(TTC, 0, tau_max)) / tau_max      # in [0, 1]

The boxes overlap along both axes only once both gaps have closed, hence the max.
Divisions use safe denominators under ``where`` so torch gradients stay finite at
``d_k = 0``, zero closing speed and on the diagonal.
"""

from __future__ import annotations

from riskflow_env._array import Array, device, namespace
from riskflow_env.geometry import to_frame

TAU_MAX = 20.0  # [s] TTC horizon; TTC is clipped to [0, TAU_MAX] and risk 0 at TAU_MAX.
MAX_INTERACTION_DISTANCE = 50.0  # [m] centre distance beyond which pairs are ignored.

FEATURE_NAMES = ("dx", "dy", "cos_dpsi", "sin_dpsi", "dvx", "dvy", "norm_distance", "risk")
NUM_PAIR_FEATURES = len(FEATURE_NAMES)


def _check_inputs(state: Array, length: Array, width: Array, valid: Array | None = None) -> None:
    if state.ndim < 2 or state.shape[-1] != 4:
        raise ValueError(f"state must have shape (..., A, 4) (x, y, v, psi); got {state.shape}")
    for name, arr in (("length", length), ("width", width), ("valid", valid)):
        if arr is not None and tuple(arr.shape) != tuple(state.shape[:-1]):
            raise ValueError(
                f"{name} must have shape (..., A) = {tuple(state.shape[:-1])}; got {arr.shape}"
            )


def _safe_sqrt(x: Array, xp) -> Array:
    """sqrt(x) for x >= 0 with a finite gradient at x = 0 (where it is 0)."""
    positive = x > 0
    return xp.where(positive, xp.sqrt(xp.where(positive, x, 1.0)), 0.0)


def _pair_geometry(state: Array, length: Array, width: Array, tau_max: float):
    """Relative kinematics of every ordered pair in i's frame, and its TTC.

    Returns a dict of (..., A, A) arrays: dx, dy [m], cos_dpsi, sin_dpsi, dvx, dvy
    [m/s], distance [m] (centre to centre), size_scale [m] and ttc [s].
    """
    xp = namespace(state, length, width)
    x, y, v, psi = (state[..., k] for k in range(4))
    cos_psi, sin_psi = xp.cos(psi), xp.sin(psi)
    vx, vy = v * cos_psi, v * sin_psi

    def pair(a: Array) -> tuple[Array, Array]:  # (..., A) -> i-view (..., A, 1), j-view (..., 1, A)
        return a[..., :, None], a[..., None, :]

    (x_i, x_j), (y_i, y_j) = pair(x), pair(y)
    (vx_i, vx_j), (vy_i, vy_j) = pair(vx), pair(vy)
    (c_i, _), (s_i, _) = pair(cos_psi), pair(sin_psi)
    (psi_i, psi_j), (len_i, len_j), (wid_i, wid_j) = pair(psi), pair(length), pair(width)

    # World-frame offsets rotated by -psi_i into i's frame.
    wx, wy, wvx, wvy = x_j - x_i, y_j - y_i, vx_j - vx_i, vy_j - vy_i
    dx, dy = to_frame(wx, wy, c_i, s_i)
    dvx, dvy = to_frame(wvx, wvy, c_i, s_i)
    cos_dpsi, sin_dpsi = xp.cos(psi_j - psi_i), xp.sin(psi_j - psi_i)

    abs_c, abs_s = xp.abs(cos_dpsi), xp.abs(sin_dpsi)
    ext_x = 0.5 * (len_i + abs_c * len_j + abs_s * wid_j)
    ext_y = 0.5 * (wid_i + abs_s * len_j + abs_c * wid_j)

    def axis_time(d: Array, dv: Array, ext: Array) -> Array:
        gap = xp.abs(d) - ext
        closing = -xp.sign(d) * dv
        # Closing within the horizon: divide only where gap / closing < tau_max, so
        # neither the value nor its gradient blows up at tiny closing speeds.
        approaching = xp.logical_and(closing > 0, closing * tau_max > gap)
        t = xp.where(approaching, gap / xp.where(approaching, closing, 1.0), tau_max)
        return xp.where(gap <= 0, 0.0, t)

    ttc = xp.clip(xp.maximum(axis_time(dx, dvx, ext_x), axis_time(dy, dvy, ext_y)), 0.0, tau_max)

    diag = xp.sqrt(length**2 + width**2)  # bounding-circle diameter [m]
    diag_i, diag_j = pair(diag)
    return {
        "dx": dx,
        "dy": dy,
        "cos_dpsi": cos_dpsi,
        "sin_dpsi": sin_dpsi,
        "dvx": dvx,
        "dvy": dvy,
        "distance": _safe_sqrt(dx**2 + dy**2, xp),
        "size_scale": 0.5 * (diag_i + diag_j),
        "ttc": ttc,
    }


def time_to_collision(state: Array, length: Array, width: Array, tau_max: float = TAU_MAX) -> Array:
    """Axis-wise TTC of every ordered pair (see the module docstring for the formula).

    Args:
      state: (..., A, 4) agent states (x [m], y [m], v [m/s], psi [rad]).
      length: (..., A) box lengths [m].
      width: (..., A) box widths [m].
      tau_max: TTC horizon [s]; opening or parallel pairs get ``tau_max``.

    Returns:
      (..., A, A) TTC [s] in [0, tau_max]; ``[..., i, j]`` is j as seen from i. No
      masking: the diagonal is 0 (a box overlaps itself); use ``pairwise_features``
      or ``pair_risk`` for masked values.
    """
    _check_inputs(state, length, width)
    return _pair_geometry(state, length, width, tau_max)["ttc"]


def risk_weight(ttc: Array, tau_max: float = TAU_MAX) -> Array:
    """TTC risk weight ``(tau_max - clip(ttc, 0, tau_max)) / tau_max``.

    Args:
      ttc: (...) time to collision [s].
      tau_max: TTC horizon [s].

    Returns:
      (...) risk in [0, 1]: 1 for boxes already overlapping, 0 at or beyond tau_max.
    """
    xp = namespace(ttc)
    return (tau_max - xp.clip(ttc, 0.0, tau_max)) / tau_max


def pairwise_features(
    state: Array,
    length: Array,
    width: Array,
    valid: Array | None = None,
    tau_max: float = TAU_MAX,
    max_distance: float = MAX_INTERACTION_DISTANCE,
) -> tuple[Array, Array]:
    """Pairwise interaction features ``e_ij`` in agent i's frame, with their mask.

    Features, in ``FEATURE_NAMES`` order: ``dx, dy`` [m] position of j; ``cos_dpsi,
    sin_dpsi`` of the relative heading ``psi_j - psi_i``; ``dvx, dvy`` [m/s] velocity of
    j relative to i; ``norm_distance`` = centre distance / ``0.5 * (sqrt(L_i^2 + W_i^2)
    + sqrt(L_j^2 + W_j^2))``, the sum of the bounding-circle radii, so ``<= 1`` means
    the bounding circles touch; ``risk`` = ``risk_weight(TTC)``.

    Args:
      state: (..., A, 4) agent states (x [m], y [m], v [m/s], psi [rad]).
      length: (..., A) box lengths [m].
      width: (..., A) box widths [m].
      valid: optional (..., A) bool; invalid agents take part in no pair.
      tau_max: TTC horizon [s].
      max_distance: pairs with centre distance above this [m] are masked.

    Returns:
      features: (..., A, A, NUM_PAIR_FEATURES), zero where ``mask`` is False.
      mask: (..., A, A) bool; False on the diagonal, for pairs with an invalid agent
        and for pairs farther apart than ``max_distance``.
    """
    geo, mask = _masked_geometry(state, length, width, valid, tau_max, max_distance)
    xp = namespace(state, length, width)
    geo["norm_distance"] = geo["distance"] / geo["size_scale"]
    geo["risk"] = risk_weight(geo["ttc"], tau_max)
    features = xp.stack([geo[name] for name in FEATURE_NAMES], axis=-1)
    return xp.where(mask[..., None], features, 0.0), mask


def _masked_geometry(
    state: Array,
    length: Array,
    width: Array,
    valid: Array | None,
    tau_max: float,
    max_distance: float,
) -> tuple[dict[str, Array], Array]:
    """``_pair_geometry`` and the pair mask of ``pairwise_features``."""
    _check_inputs(state, length, width, valid)
    xp = namespace(state, length, width)
    geo = _pair_geometry(state, length, width, tau_max)
    num_agents = state.shape[-2]
    eye = xp.eye(num_agents, dtype=xp.bool, device=device(state))
    mask = xp.logical_and(~eye, geo["distance"] <= max_distance)
    if valid is not None:
        valid = xp.astype(valid, xp.bool)
        mask = mask & valid[..., :, None] & valid[..., None, :]
    return geo, mask


def pair_risk(
    state: Array,
    length: Array,
    width: Array,
    valid: Array | None = None,
    tau_max: float = TAU_MAX,
    max_distance: float = MAX_INTERACTION_DISTANCE,
) -> tuple[Array, Array]:
    """The ``risk`` channel of :func:`pairwise_features` and its mask, without building
    the other features (what the rewards need when no observation is asked for).

    Args: as ``pairwise_features``.

    Returns:
      risk: (..., A, A) in [0, 1], 0 wherever ``mask`` is False.
      mask: (..., A, A) bool, as ``pairwise_features``.
    """
    geo, mask = _masked_geometry(state, length, width, valid, tau_max, max_distance)
    xp = namespace(state, length, width)
    return xp.where(mask, risk_weight(geo["ttc"], tau_max), 0.0), mask
