"""M4World world model: scene language, procedural sensor simulator, dataset, neural model.

This package knows nothing of gymnasium or highway-env (DESIGN.md, "Data flow").
"""

from world_model.observation import Observation
from world_model.scene import (
    CATEGORIES,
    CATEGORY_SIZES,
    NAMED_COLORS,
    TIMES_OF_DAY,
    WEATHERS,
    Box3D,
    EgoState,
    LaneLine,
    MapGeometry,
    SceneFrame,
    SceneObject,
    ScenePrompt,
)
from world_model.sensors import BevSpec, CameraRig, CameraSpec, LidarSpec, default_rig

__all__ = [
    "CATEGORIES",
    "CATEGORY_SIZES",
    "NAMED_COLORS",
    "TIMES_OF_DAY",
    "WEATHERS",
    "BevSpec",
    "Box3D",
    "CameraRig",
    "CameraSpec",
    "EgoState",
    "LaneLine",
    "LidarSpec",
    "MapGeometry",
    "Observation",
    "SceneFrame",
    "SceneObject",
    "ScenePrompt",
    "default_rig",
]
