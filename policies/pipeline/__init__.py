"""The planning cycle of every learned scene policy, as a list of stages.

* :mod:`~policies.pipeline.state`: ``PlannerState``, what a policy keeps of one scene
  between cycles (one value, passed in and returned);
* :mod:`~policies.pipeline.plan_set`: ``PlanSet``, the typed plans the stages of one cycle
  hand each other (B scenes, torch, ego frame);
* :mod:`~policies.pipeline.stages`: the shared stages (encode, rank, generate, stitch,
  decode, avoid, stand, emit, hold, restitch) and ``plan_scenes``, which runs a policy's
  stages once for B scenes;
* :mod:`~policies.pipeline.policy`: ``PipelinePolicy`` (schedule, plan buffer, seeding,
  spawned copies for many scenes).

A method is a ``PipelinePolicy`` with its list of stages: RiskFlow
(:mod:`policies.riskflow.policy`), the unguided generator and STRIVE-style
(:mod:`policies.baselines`), the guided diffusion baselines.
docs/explanation/architecture.md draws it.
"""
