"""The scene raster: what a SceneFrame implies per sensor, drawn geometrically beside the model.

The world model's observations reach the VAE decoder by two paths: SceneFrame -> control tokens
-> causal student -> latents, which give the light and the colour, and SceneFrame -> this raster,
which gives where the road, the lane lines and each vehicle and its paint are (feed the decoder
zeros for latents and those are still drawn). Its modules:

* :mod:`~world_model.raster.classes`: the label maps' classes, planes and byte codes (numpy only,
  so that the model's config and decoder read them without the renderer);
* :mod:`~world_model.raster.maps`: :class:`~world_model.raster.maps.SceneRaster`, each camera's
  label, paint and surface maps and the LiDAR view's nearness at full resolution, which the
  conditions carry to the decoder (:func:`~world_model.model.conditions.build_condition_arrays`);
* :mod:`~world_model.raster.crops`: each object's reference crop (its image description), cut
  causally from the procedural simulator's views as a rollout goes, or replayed from a recording.

Import the modules themselves: this package imports none of them, so that reading the classes
never loads the renderer.
"""
