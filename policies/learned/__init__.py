"""What every learned adversary shares (RiskFlow, STRIVE-style, the diffusion baselines).

* model input: :mod:`~policies.learned.window_types` (``Window``, ``WindowBatch``:
  a scene as the model sees it, docs/how-to/windows.md), :mod:`~policies.learned.windows`
  (building them), :mod:`~policies.learned.data`, :mod:`~policies.learned.batches`,
  :mod:`~policies.learned.data_cache`, :mod:`~policies.learned.synthetic`;
* the network: :mod:`~policies.learned.config`, :mod:`~policies.learned.encoder`
  (with :mod:`~policies.learned.map_encoder`, :mod:`~policies.learned.attention`,
  :mod:`~policies.learned.embeddings`, :mod:`~policies.learned.packing`: per-agent
  layers on the real agents only), :mod:`~policies.learned.generator` (the
  velocity head every generator kind trains), :mod:`~policies.learned.checkpoint`;
* sampling and validation of a one-call generator: :mod:`~policies.learned.sampler`,
  :mod:`~policies.learned.validation`, :mod:`~policies.learned.ema`;
* the adversary's loop: :mod:`~policies.learned.adversary_config` (the shared options),
  :mod:`~policies.learned.plan_stitching` (re-plans blended into the executed plan),
  :mod:`~policies.learned.plan_avoidance` (the avoidance steps),
  :mod:`~policies.pipeline.batched` (B scenes, one planning call),
  :mod:`~policies.learned.ranking` (TTC causal ranking of the controllable set),
  :mod:`~policies.learned.guidance_losses` (the adversarial and map objective),
  :mod:`~policies.learned.plan_penalties` (collision / off-road penalties of plans).

The planning cycle that strings these together is :mod:`policies.pipeline`. Nothing here
imports :mod:`policies.riskflow` or :mod:`policies.baselines` (docs/explanation/architecture.md);
import the submodules directly.
"""
