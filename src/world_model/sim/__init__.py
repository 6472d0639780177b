"""Procedural multi-camera + LiDAR + BEV sensor simulator (ground truth, fast non-neural backend).

Knows nothing of gymnasium or highway-env. See :class:`ProceduralSimulator`.
"""

from world_model.sim.config import SimConfig
from world_model.sim.lighting import Lighting, lighting_for
from world_model.sim.mosaic import mosaic
from world_model.sim.simulator import ProceduralSimulator

__all__ = ["Lighting", "ProceduralSimulator", "SimConfig", "lighting_for", "mosaic"]
