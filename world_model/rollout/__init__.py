"""The pipeline that streams rollouts of a trained world model, SceneFrames in, observations out.

* :mod:`~world_model.rollout.runtime`: :func:`~world_model.rollout.runtime.load_world_model`, a
  checkpoint bundle's modules (:class:`~world_model.rollout.runtime.WorldModel`): first frames
  from the reference model, decoding;
* :mod:`~world_model.rollout.builder`: a SceneFrame's condition arrays (map raster, text, crops'
  features, the scene raster of :mod:`world_model.raster`);
* :mod:`~world_model.rollout.conditions`: the CPU side of a batch of rollouts (first frames,
  reference crops, arrays), one owner for the env, its simulation workers and the report;
* :mod:`~world_model.rollout.batch`: the model side, one batched causal chunk per step;
* :mod:`~world_model.rollout.timing`: an optional timer of the pipeline's stages.
"""
