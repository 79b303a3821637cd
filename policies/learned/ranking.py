"""TTC causal ranking: which vehicles form the controllable set ``A_c``.

RiskFlow (Lan et al. 2026, "RiskFlow: Fast and Faithful Safety-Critical Traffic Scenario
Generation") guides only the top-K *critical* agents, found, as in CCDiff (Lin et al.
2025, "Causal Composition Diffusion Model for Closed-loop Traffic Generation"), from the
structure of the scene's interactions (docs/explanation/architecture.md):

1. **Risk graph.** The pairwise TTC risk ``r_ij`` (``riskflow_env.risk``, in [0, 1]; 0 for
   pairs beyond 50 m) is symmetrised, ``w_ij = max(r_ij, r_ji)`` (TTC is measured in
   i's frame, so the two directions can differ), and the pairs with ``w_ij > threshold``
   (0.5: TTC below 10 s) are the edges.
2. **Interacting groups = connected components** of that graph. Components rather than
   maximal cliques because a *causal* conflict is a chain: A cuts in ahead of B, B
   brakes in front of C, and C never conflicts with A directly. A clique splits that
   chain into pairs; a component keeps it one group. Components are also unique,
   computed in O(A^2) (``scipy.sparse.csgraph.connected_components``) and need no
   exponential clique enumeration. The ego is a node: its conflicts make a group
   critical, though the ego itself is never controllable.
3. **Scores.** A group's risk is the sum of its edge weights; each agent's score is the
   accumulated risk of the groups it is in, i.e. its component's risk (0 for agents in
   no group).
4. **Top K.** Candidates (live non-ego agents) are ordered by score, then by their own
   summed edge risk ("strength": who carries the group), then by their largest risk to
   anyone (below the threshold too: that fills shortfalls when fewer than K agents are in
   groups), then by distance to the ego (nearer first), then by slot index. The order is
   total, so ``A_c`` is deterministic. ``k = 0`` gives an empty set, ``k = "all"`` every
   candidate.

With guidance target ``"ego"`` (stress testing an ego planner) ``A_c`` is one attacker at
most (:func:`ego_attacker`), so that the ego meets one adversary at a time, not a swarm:

* nobody attacks an ego (nearly) at rest, slower than ``MIN_ATTACK_SPEED``: a standing car
  struck is the striker's failure, not the planner's;
* only a vehicle ahead of or beside the ego (its centre ahead of the ego's rear bumper) may
  attack, so that it strikes the ego's front or side, where the ego sees it and can brake
  or swerve, never its rear;
* only a moving vehicle, at ``MIN_ATTACKER_SPEED`` or faster, may attack. Beside a road
  lined with parked cars the TTC ranking puts a parked car first; chosen, it did not pull
  out (its speed floor is its speed now, 0, so nothing made it), and the one attack of the
  scene was spent on a car that never moved (docs/explanation/results.md, "Only a moving
  vehicle attacks");
* the last cycle's attacker stays while it is eligible (hopping to another vehicle every
  cycle would bend several plans toward the ego in turn); a new one is the eligible
  candidate at the highest TTC risk with the ego, then the nearest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from policies.learned.window_types import Window
from riskflow_env.dynamics import SPEED
from riskflow_env.risk import FEATURE_NAMES

DEFAULT_THRESHOLD = 0.5  # risk above which a pair is an edge (TTC < 10 s with tau_max = 20 s)
MIN_ATTACK_SPEED = 2.0  # [m/s] ego speed below which target "ego" guides no vehicle
MIN_ATTACKER_SPEED = 0.5  # [m/s] a vehicle slower than this (parked, waiting) never attacks
RISK_CHANNEL = FEATURE_NAMES.index("risk")
NO_GROUP = -1


@dataclass(frozen=True)
class Ranking:
    """The controllable set and how it was chosen.

    Attributes:
        controllable: (A,) bool, the set ``A_c``.
        scores: (A,) accumulated group risk of each agent (0 outside any group).
        groups: (A,) int group label (component id, numbered by lowest slot), ``NO_GROUP``
            for agents in no group (no edge) and for invalid agents.
        order: (M,) int candidate slots (live non-ego agents), most critical first;
            ``A_c`` is a prefix of it.
    """

    controllable: np.ndarray
    scores: np.ndarray
    groups: np.ndarray
    order: np.ndarray


def check_k(k: int | str) -> int | str:
    """Validate ``k``: an int >= 0 or ``"all"``."""
    if k == "all" or (isinstance(k, (int, np.integer)) and not isinstance(k, bool) and k >= 0):
        return k if isinstance(k, str) else int(k)
    raise ValueError(f"k must be an int >= 0 or 'all', got {k!r}")


def risk_graph(risk: np.ndarray, valid: np.ndarray, threshold: float = DEFAULT_THRESHOLD):
    """Symmetric edge weights of the risk graph.

    Args:
        risk: (A, A) TTC risk in [0, 1], ``risk[i, j]`` = j seen from i; diagonal ignored.
        valid: (A,) bool agents that take part.
        threshold: edges are pairs with ``max(r_ij, r_ji) > threshold``.

    Returns:
        ``(weights, edges)``: (A, A) float64 symmetric risk ``w_ij`` (0 on the diagonal and
        for invalid agents) and (A, A) bool edges.
    """
    weights = np.maximum(risk, risk.T).astype(np.float64)
    pair_valid = valid[:, None] & valid[None, :]
    np.fill_diagonal(pair_valid, False)
    weights = np.where(pair_valid, weights, 0.0)
    return weights, weights > threshold


def interaction_groups(edges: np.ndarray) -> np.ndarray:
    """(A,) component label of each agent with at least one edge, ``NO_GROUP`` otherwise.

    Labels are numbered in the order of each component's lowest slot.
    """
    _, labels = connected_components(csr_matrix(edges), directed=False)
    in_group = edges.any(axis=1)
    groups = np.full(edges.shape[0], NO_GROUP, dtype=np.int64)
    _, first = np.unique(labels[in_group], return_index=True)
    for new, old in enumerate(labels[in_group][np.sort(first)]):
        groups[(labels == old) & in_group] = new
    return groups


def causal_ranking(
    risk: np.ndarray,
    valid: np.ndarray,
    k: int | str,
    *,
    ego: int = 0,
    threshold: float = DEFAULT_THRESHOLD,
    distance_to_ego: np.ndarray | None = None,
) -> Ranking:
    """The top-K controllable set ``A_c`` of one scene (module docstring).

    Args:
        risk: (A, A) TTC risk in [0, 1] (``riskflow_env.risk.pair_risk`` or the ``risk``
            channel of a window's ``pair_features``).
        valid: (A,) bool agents present at the current step; others are never chosen.
        k: size of ``A_c`` (int >= 0; fewer if fewer candidates) or ``"all"``.
        ego: slot of the agent under test; never in ``A_c``.
        threshold: edge threshold on the symmetrised risk.
        distance_to_ego: (A,) [m] centre distance to the ego, a tie-break (nearer
            first); None skips it.

    Returns:
        the :class:`Ranking`.
    """
    k = check_k(k)
    risk = np.asarray(risk, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    num_agents = valid.shape[0] if valid.ndim == 1 else -1
    if risk.shape != (num_agents, num_agents) or not np.all(np.isfinite(risk)):
        raise ValueError(
            f"risk must be a finite (A, A) array with A = len(valid) = {num_agents}, "
            f"got shape {risk.shape}"
        )
    if not 0 <= ego < num_agents:
        raise ValueError(f"ego must be a slot in [0, {num_agents}), got {ego}")
    if distance_to_ego is None:
        distance_to_ego = np.zeros(num_agents)
    distance_to_ego = np.asarray(distance_to_ego, dtype=np.float64)
    if distance_to_ego.shape != (num_agents,):
        raise ValueError(f"distance_to_ego must have shape ({num_agents},) [m]")

    weights, edges = risk_graph(risk, valid, threshold)
    groups = interaction_groups(edges)
    rows, cols = np.nonzero(np.triu(edges, 1))
    group_risk = np.bincount(
        groups[rows], weights=weights[rows, cols], minlength=int(groups.max()) + 1
    )
    scores = np.zeros(num_agents)
    in_group = groups >= 0
    scores[in_group] = group_risk[groups[in_group]]
    strength = np.where(edges, weights, 0.0).sum(axis=1)
    largest = weights.max(axis=1)

    candidates = valid.copy()
    candidates[ego] = False
    slots = np.flatnonzero(candidates)
    # lexsort: last key first; negate the "larger first" keys.
    keys = (slots, distance_to_ego[slots], -largest[slots], -strength[slots], -scores[slots])
    order = slots[np.lexsort(keys)]
    count = order.size if k == "all" else min(k, order.size)
    controllable = np.zeros(num_agents, dtype=bool)
    controllable[order[:count]] = True
    return Ranking(controllable=controllable, scores=scores, groups=groups, order=order)


def rank_window(
    window: Window,
    k: int | str,
    threshold: float = DEFAULT_THRESHOLD,
    candidates: np.ndarray | None = None,
    *,
    attack_ego: bool = False,
    attacker: int | None = None,
) -> Ranking:
    """:func:`causal_ranking` of one window (docs/how-to/windows.md; slot 0 is the ego);
    with ``attack_ego``, narrowed to one attacker (:func:`ego_attacker`).

    Uses the ``risk`` channel of ``pair_features`` (already masked beyond 50 m), the
    ``agent_mask`` and the current positions of ``history`` for the distance tie-break.
    Slots are window slots.

    Args:
        window: the window.
        k: size of ``A_c`` or ``"all"``.
        threshold: edge threshold.
        candidates: optional (A,) bool, agents that may be chosen (e.g. the live ones);
            every agent of the window still takes part in the risk graph.
        attack_ego: guidance target ``"ego"``: ``A_c`` is one attacker at most.
        attacker: with ``attack_ego``, the window slot of the last cycle's attacker, kept
            while it is eligible; None: none.
    """
    if attack_ego:
        ranking = rank_window(window, k, threshold, candidates)
        return ego_attacker(ranking, window, k, attacker)
    risk = np.asarray(window.pair_features)[..., RISK_CHANNEL]
    current = np.asarray(window.history)[:, -1, :2]
    distance = np.linalg.norm(current - current[0], axis=-1)
    agent_mask = np.asarray(window.agent_mask, dtype=bool)
    ranking = causal_ranking(risk, agent_mask, k, threshold=threshold, distance_to_ego=distance)
    if candidates is None:
        return ranking
    order = ranking.order[np.asarray(candidates, dtype=bool)[ranking.order]]
    count = order.size if k == "all" else min(int(k), order.size)
    controllable = np.zeros_like(agent_mask)
    controllable[order[:count]] = True
    return Ranking(controllable, ranking.scores, ranking.groups, order)


def ego_attacker(ranking: Ranking, window: Window, k: int | str, previous: int | None) -> Ranking:
    """``A_c`` of guidance target ``"ego"``: one attacker at most (module docstring).

    Args:
        ranking: the window's ranking (:func:`rank_window`); its ``order`` holds the
            candidates (live non-ego slots).
        window: the window (scene frame: the ego at the origin, heading along +x).
        k: the size of ``A_c`` asked for: 0 guides no vehicle, any other one.
        previous: window slot of the last cycle's attacker, kept while it is eligible;
            None: none.

    Returns:
        the ranking with ``controllable`` the attacker's slot alone, or no slot (``k = 0``,
        the ego slower than ``MIN_ATTACK_SPEED``, or no eligible candidate: ahead of or
        beside the ego and at ``MIN_ATTACKER_SPEED`` or faster).
    """
    current = np.asarray(window.history, dtype=np.float64)[:, -1]  # (A, 4), the ego at 0
    candidates = ranking.order
    if k == 0 or current[0, SPEED] < MIN_ATTACK_SPEED:
        candidates = candidates[:0]
    rear_bumper = -0.5 * float(window.length[0])  # [m] along the ego's heading
    ahead = current[candidates, 0] > rear_bumper
    eligible = candidates[ahead & (current[candidates, SPEED] >= MIN_ATTACKER_SPEED)]
    if previous is not None and previous in eligible:
        chosen = [previous]
    else:
        risk = np.asarray(window.pair_features)[..., RISK_CHANNEL]
        to_ego = np.maximum(risk[0], risk[:, 0])[eligible]  # TTC risk with the ego
        distance = np.linalg.norm(current[eligible, :2], axis=-1)
        chosen = eligible[np.lexsort((distance, -to_ego))][:1]  # riskiest, then nearest
    controllable = np.zeros_like(ranking.controllable)
    controllable[chosen] = True
    return Ranking(controllable, ranking.scores, ranking.groups, ranking.order)


__all__ = [
    "DEFAULT_THRESHOLD",
    "MIN_ATTACK_SPEED",
    "MIN_ATTACKER_SPEED",
    "NO_GROUP",
    "Ranking",
    "causal_ranking",
    "check_k",
    "ego_attacker",
    "interaction_groups",
    "rank_window",
    "risk_graph",
]
