"""Procedural multi-camera + LiDAR + BEV sensor simulator (ground truth, fast non-neural backend).

``ProceduralSimulator.render(frame)`` turns a :class:`~world_model.scene.SceneFrame` into an
:class:`~world_model.observation.Observation`; rendering is a pure, deterministic function of the
frame. Knows nothing of gymnasium or highway-env. How it works, module by module:

* ``texture`` / ``ground``: the road is a world-aligned label texture, rasterized lazily in tiles;
  camera pixels below the horizon hit the road at points fixed in the ego frame (precomputed per
  rig), so a frame is one affine transform + one texture lookup + one palette lookup per pixel.
  Per-pixel light and fog are baked into a palette per (rig, weather, time of day).
* ``shapes`` / ``mesh`` / ``scene_mesh`` / ``objects``: each category is a few convex parts with
  decals (windows, lamps, stripes), painted far-to-near per view with near-plane clipping.
* ``lidar``: exact ray casting against the road plane and every object's full 3D box.
* ``lighting`` / ``precipitation``: sky, sun, fog, lamps at night, rain streaks and snow.
* ``labels``: per-camera semantic label maps (sky, off-road, road, marking, object classes) at
  any resolution, the ground truth of layout scores and layout conditioning.
* ``mosaic``: one overview image; ``demo``: small deterministic scenes for benchmarks and docs.
"""

from world_model.sim.config import SimConfig
from world_model.sim.labels import LabelRasterizer, label_maps
from world_model.sim.lighting import Lighting, lighting_for
from world_model.sim.mosaic import mosaic
from world_model.sim.simulator import ProceduralSimulator

__all__ = [
    "LabelRasterizer",
    "Lighting",
    "ProceduralSimulator",
    "SimConfig",
    "label_maps",
    "lighting_for",
    "mosaic",
]
