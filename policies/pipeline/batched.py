"""``BatchedAdversary``: one learned adversary driving the traffic of B scenes at once.

A :class:`~policies.pipeline.policy.PipelinePolicy` plans one scene per call. To
drive many scenes (a vectorised env, an evaluation over many scenes) the adversary holds
one copy per scene (:meth:`PipelinePolicy.spawn`: the model and options shared, the
planner state its own) and plans every scene that is due
in **one call** (:func:`~policies.pipeline.stages.plan_scenes`): for
``RiskFlowAdversary`` (and the unguided generator) one encoder pass, one generator pass
and one guidance loop over all those scenes' controllable rows, agents padded per scene
and masked. Scenes re-plan on their own schedules: a scene reset at another step, or
with another planning phase, is planned in the calls where it is due, and the others
keep playing their buffered plans.

Each scene's plans are those of planning it alone with a policy of its seed, to float
rounding (tests/policies/pipeline/test_batched.py); the same seeds give the
same batched rollout, bit for bit, on one machine. Scene ``b``'s seed is ``seeds[b]``
(default ``policy.seed + b``): its noise of cycle ``c`` of its episode ``e`` comes from
``(seeds[b], e, c)``, whatever the other scenes do.

    batch = BatchedAdversary(RiskFlowAdversary(k=5), num_scenes=len(envs))
    batch.reset([env.view() for env in envs])
    actions = batch.act([env.view() for env in envs])  # a dict per scene

The STRIVE-style baseline batches its latent optimisation the same way (one generator
forward and backward pass per step over every scene's ``A_c`` rows), and the diffusion
baselines their reverse chains (one denoiser pass per level for every scene, in the base
chain and in the guided one).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from policies.pipeline.policy import PipelinePolicy
from policies.pipeline.stages import plan_scenes, prepare_maps
from riskflow_env.config import is_integer
from riskflow_env.view import SceneView


class BatchedAdversary:
    """B scenes driven by copies of one learned adversary (module docstring).

    Args:
        policy: the adversary (its model and options); it is not used itself, each scene
            gets a copy.
        num_scenes: B >= 1.
        seeds: B noise seeds (ints >= 0), one per scene; None: ``policy.seed + b``.
    """

    def __init__(
        self, policy: PipelinePolicy, num_scenes: int, seeds: Sequence[int] | None = None
    ) -> None:
        if not isinstance(policy, PipelinePolicy):
            raise TypeError(
                f"policy must be a learned adversary (a PipelinePolicy), got {type(policy)}"
            )
        if not is_integer(num_scenes) or num_scenes < 1:
            raise ValueError(f"num_scenes must be an int >= 1, got {num_scenes!r}")
        if seeds is None:
            seeds = [policy.seed + index for index in range(num_scenes)]
        seeds = list(seeds)
        if len(seeds) != num_scenes:
            raise ValueError(f"seeds must hold num_scenes = {num_scenes} seeds, got {len(seeds)}")
        self.scenes: tuple[PipelinePolicy, ...] = tuple(policy.spawn(seed) for seed in seeds)
        self.last_planned: tuple[int, ...] = ()

    def __len__(self) -> int:
        return len(self.scenes)

    def _check_views(self, views: Sequence[SceneView]) -> list[SceneView]:
        views = list(views)
        if len(views) != len(self.scenes):
            raise ValueError(f"views must hold one view per scene ({len(self)}), got {len(views)}")
        return views

    def reset(self, views: Sequence[SceneView]) -> None:
        """New episodes in every scene (``views[b]`` is scene ``b`` after ``env.reset``)."""
        for scene, view in zip(self.scenes, self._check_views(views), strict=True):
            scene.reset(view)

    def reset_scene(self, index: int, view: SceneView, seed: int | None = None) -> None:
        """A new episode in scene ``index`` only (e.g. a vector env's autoreset); with
        ``seed`` its noise restarts as a fresh copy with that seed would."""
        if not (isinstance(index, (int, np.integer)) and 0 <= index < len(self)):
            raise ValueError(f"index must be a scene index in [0, {len(self)}), got {index!r}")
        if seed is not None:
            self.scenes[index].reseed(seed)
        self.scenes[index].reset(view)

    def act(self, views: Sequence[SceneView]) -> list[dict[str, np.ndarray]]:
        """The next action of every live non-ego vehicle of each scene (a dict per scene,
        as ``ScenePolicy.act``); the scenes due to re-plan are planned in one call
        (their indices: ``last_planned``)."""
        views = self._plan_due(views)
        return [scene.emit(view) for scene, view in zip(self.scenes, views, strict=True)]

    def act_array(
        self, views: Sequence[SceneView], running: np.ndarray | None = None
    ) -> np.ndarray:
        """:meth:`act` as one (B, A, 2) array (accel [m/s^2], yaw rate [rad/s]), zeros
        for the slots no plan drives (the ego, empty slots): what batched stepping takes.

        Args:
            views: one view per scene.
            running: (B,) bool, the scenes still running (None: all); the others (their
                episode over, e.g. an evaluation's scenes that ended early) are neither
                planned nor asked, and get zeros.
        """
        views = self._plan_due(views, running)
        actions = np.zeros((len(self), views[0].num_agents, 2))
        for index in self._running(running):
            actions[index] = self.scenes[index].emit_array(views[index])
        return actions

    def _running(self, running: np.ndarray | None) -> np.ndarray:
        """The indices of the running scenes (all when ``running`` is None)."""
        if running is None:
            return np.arange(len(self))
        running = np.asarray(running)
        if running.shape != (len(self),) or running.dtype != bool:
            raise ValueError(
                f"running must be a ({len(self)},) bool array, got {running.dtype} {running.shape}"
            )
        return np.flatnonzero(running)

    def _plan_due(
        self, views: Sequence[SceneView], running: np.ndarray | None = None
    ) -> list[SceneView]:
        """Plan the running scenes due to re-plan, in one call; the checked views."""
        views = self._check_views(views)
        due = [i for i in self._running(running) if self.scenes[i].due(views[i])]
        if due:
            self.plan(views, due)
        else:
            self.last_planned = ()
        return views

    def plan(self, views: Sequence[SceneView], scenes: Sequence[int] | None = None) -> None:
        """Plan the scenes ``scenes`` (indices; None: all) now, in one call; their buffers
        restart at their ``view.step``.

        Every scene's map is stacked once for the guidance's map term and kept while the
        scenes keep their maps.
        """
        views = self._check_views(views)
        indices = list(range(len(self))) if scenes is None else [int(i) for i in scenes]
        if not indices or any(not 0 <= i < len(self) for i in indices):
            raise ValueError(f"scenes must be non-empty indices in [0, {len(self)}), got {scenes}")
        if len(set(indices)) != len(indices):
            raise ValueError(f"scenes must not repeat an index, got {scenes}")
        planner = self.scenes[indices[0]]
        if len({id(view.map) for view in views}) > 1:
            prepare_maps(planner, [view.map for view in views])
        plan_scenes([self.scenes[i] for i in indices], [views[i] for i in indices])
        self.last_planned = tuple(indices)


__all__ = ["BatchedAdversary"]
