"""``SceneBatch``: N independent episodes of ``riskflow_v0`` stepped as one batch.

:mod:`riskflow_env.batched` steps scenes in lockstep on one shared map. A vector env
(``policies.rl.vector_env.EgoVectorEnv``) needs more: each scene draws its own scenario
(own map, own agents) from the scenario source, resets on its own when its episode ends,
and keeps the 31-step history that scene policies read from their
:class:`~riskflow_env.view.SceneView`. ``SceneBatch`` keeps

* one :class:`~riskflow_env.env.RiskFlowParallelEnv` per scene, used **only to reset**
  it: the scenario draw from the scene's own seeded generator, the slot selection, the
  log ends, the initial observations and infos are the env's own (nothing re-written);
* the batched :class:`~riskflow_env.state.SceneState` (``history`` (N, A, 31, 4)) with a
  per-scene step counter ``step`` (N, 1), stepped by **one** call of
  :func:`riskflow_env.simulator.transition` for all scenes and agents;
* the scenes' maps in a :class:`~riskflow_env.maps.MapStack` (one SDF lookup for every
  scene, each point on its own scene's map), or the one map they share.

So scene ``b`` of a batch follows, to float rounding (the map lookup goes through the
stack), the same episode as a ``RiskFlowParallelEnv`` reset with the same seed and given
the same actions. Arrays are numpy (float64, as in the env).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from riskflow_env import simulator
from riskflow_env.config import EnvConfig
from riskflow_env.env import RiskFlowParallelEnv
from riskflow_env.maps import DrivableMap, MapStack
from riskflow_env.scenarios import Scenario, ScenarioSource, as_source, shipped_bank
from riskflow_env.simulator import Transition
from riskflow_env.state import SceneState
from riskflow_env.view import SceneView

MAX_STACK_BYTES = 256 * 2**20  # [bytes] SDF tables kept for scenes to come back to
_ARRAYS = ("history", "history_valid", "length", "width", "present", "active", "last_action")


class SceneBatch:
    """N scenes of ``riskflow_v0`` with their own episodes, stepped together (module
    docstring).

    Args:
        num_scenes: N >= 1.
        config: the env configuration shared by the scenes (None: ``EnvConfig()``).
        scenarios: the scenario source every scene draws from (as ``parallel_env``'s
            ``scenarios``; None: the shipped evaluation bank).
    """

    def __init__(
        self,
        num_scenes: int,
        config: EnvConfig | None = None,
        scenarios: ScenarioSource | Sequence[Scenario] | Scenario | None = None,
    ) -> None:
        if isinstance(num_scenes, bool) or not isinstance(num_scenes, (int, np.integer)):
            raise TypeError(f"num_scenes must be an int >= 1, got {type(num_scenes).__name__}")
        if num_scenes < 1:
            raise ValueError(f"num_scenes must be an int >= 1, got {num_scenes}")
        source = as_source(scenarios) if scenarios is not None else shipped_bank("eval")
        self.envs = tuple(
            RiskFlowParallelEnv(config=config, scenarios=source) for _ in range(int(num_scenes))
        )
        self.config = self.envs[0].config
        self.agent_names = tuple(self.envs[0].possible_agents)
        self._masks = simulator.termination_masks(self.config)
        self.state: SceneState | None = None
        self.log_end: np.ndarray | None = None  # (N, A) int, when the env asks for it
        self._rows = [np.zeros(0, dtype=int)] * len(self.envs)  # scenario row of each slot
        self._maps: MapStack | None = None
        self._lookup: Any = None

    def __len__(self) -> int:
        return len(self.envs)

    def reset(
        self,
        seeds: Sequence[int | None],
        options: Mapping[str, Any] | Sequence[Mapping[str, Any] | None] | None = None,
    ) -> tuple[list[np.ndarray], list[dict]]:
        """Reset every scene (scene ``b`` with ``seeds[b]``, ``options`` as in
        :meth:`reset_scenes`); each scene's observations and infos per agent (the env's
        dicts)."""
        return self.reset_scenes(range(len(self)), seeds, options)

    def reset_scenes(
        self,
        indices: Sequence[int],
        seeds: Sequence[int | None],
        options: Mapping[str, Any] | Sequence[Mapping[str, Any] | None] | None = None,
    ) -> tuple[list[dict], list[dict]]:
        """Reset the scenes ``indices`` (scene ``indices[i]`` with ``seeds[i]``; None: its
        generator goes on), as ``RiskFlowParallelEnv.reset`` does.

        Args:
            indices: the scenes to reset.
            seeds: one seed (or None) per scene of ``indices``.
            options: the env's reset options for every scene (e.g. ``{"scenario": s}``),
                or a list of them, one per scene of ``indices`` (each scene its own
                scenario).

        Returns:
            the reset scenes' observation dicts and info dicts (agent -> value).
        """
        indices = [int(index) for index in indices]
        if len(seeds) != len(indices):
            raise ValueError(f"seeds must hold one seed per scene ({len(indices)}), got {seeds}")
        if options is None or isinstance(options, Mapping):
            options = [options] * len(indices)
        elif len(options) != len(indices):
            raise ValueError(
                f"options must be one mapping or a list of one per scene ({len(indices)}), "
                f"got {len(options)}"
            )
        observations, infos, states = [], [], []
        for index, seed, scene_options in zip(indices, seeds, options, strict=True):
            rows, agent_infos = self.envs[index].reset(seed=seed, options=scene_options)
            observations.append(rows)
            infos.append(agent_infos)
            states.append(self.envs[index].scene)
        self._write(indices, states)
        return observations, infos

    def _write(self, indices: list[int], states: list[SceneState]) -> None:
        """Put freshly reset single-scene states into rows ``indices`` of the batch (new
        arrays: views handed out earlier keep theirs)."""
        if self.state is None or len(indices) == len(self):
            batch = SceneState.stack([self.envs[i].scene for i in range(len(self))])
            step = np.zeros((len(self), 1), dtype=np.int64)
            self.state = batch.replace(step=step)
        else:
            fresh = SceneState.stack(states)
            changes = {}
            for name in _ARRAYS:
                array = getattr(self.state, name).copy()
                array[indices] = getattr(fresh, name)
                changes[name] = array
            step = self.state.step.copy()
            step[indices] = 0
            self.state = self.state.replace(step=step, **changes)
        for index in indices:
            self._rows[index] = self.envs[index].view().scenario_rows
        if self.config.leave_when_log_ends:
            log_end = np.zeros((len(self), self.config.max_agents), dtype=np.int64)
            if self.log_end is not None:
                log_end[:] = self.log_end
            for index in indices:
                rows, scenario = self._rows[index], self.envs[index].scenario
                log_end[index] = simulator.log_end_steps(
                    scenario, rows[rows >= 0], self.config.max_agents
                )
            self.log_end = log_end
        self._update_maps()

    def _update_maps(self) -> None:
        """The map lookup of the current scenes: their one map, or a stack of every map
        seen so far (rebuilt, only when a new map comes, with it added; restarted from the
        current maps when the tables would pass ``MAX_STACK_BYTES``)."""
        maps = [env.map for env in self.envs]
        if all(m is maps[0] for m in maps):
            self._lookup = maps[0]
            return
        if self._maps is None or any(id(m) not in self._maps.positions for m in maps):
            unique = list({id(m): m for m in maps}.values())
            kept = [] if self._maps is None else list(self._maps.maps)
            if sum(m.sdf.nbytes for m in kept + unique) > MAX_STACK_BYTES:
                kept = []  # bound the table: start again from the current maps
            known = {id(m) for m in kept}
            self._maps = MapStack(kept + [m for m in unique if id(m) not in known])
        index = np.array([self._maps.positions[id(m)] for m in maps], dtype=np.int64)
        self._lookup = self._maps.select(index)

    @property
    def map_lookup(self) -> DrivableMap | MapStack.Selection:
        """What :func:`~riskflow_env.simulator.transition` looks the SDF up in: the shared
        map, or each scene's own map through the stack."""
        return self._lookup

    def scene_state(self, index: int) -> SceneState:
        """Scene ``index``'s state as a one-scene :class:`SceneState` (arrays shared)."""
        state = self._checked_state()
        arrays = {name: getattr(state, name)[index] for name in _ARRAYS}
        return SceneState(step=int(state.step[index, 0]), **arrays)

    def views(self) -> list[SceneView]:
        """A read-only :class:`SceneView` of every scene (for scene policies)."""
        dt = self.config.dynamics.dt
        views = []
        for index, env in enumerate(self.envs):
            scene, rows = self.scene_state(index), self._rows[index]
            views.append(SceneView.from_state(scene, env.scenario, rows, self.agent_names, dt))
        return views

    def step(self, actions: np.ndarray, observations: bool = True) -> Transition:
        """Advance every scene by ``dt`` in one :func:`~riskflow_env.simulator.transition`.

        Args:
            actions: (N, A, 2) (accel [m/s^2], yaw rate [rad/s]); rows of inactive slots
                are ignored; clipped to the dynamics bounds.
            observations: compute the observations.
        """
        state = self._checked_state()
        expected = (len(self), self.config.max_agents, 2)
        if getattr(actions, "shape", None) != expected:
            raise ValueError(
                f"actions must have shape (N, A, 2) = {expected}, got "
                f"{getattr(actions, 'shape', type(actions).__name__)}"
            )
        self.state, transition = simulator.transition(
            state,
            actions,
            self._lookup,
            self.config,
            observations=observations,
            log_end=self.log_end,
            masks=self._masks,
        )
        return transition

    def _checked_state(self) -> SceneState:
        if self.state is None:
            raise RuntimeError("the scenes have not been reset yet: call reset() first")
        return self.state


__all__ = ["SceneBatch"]
