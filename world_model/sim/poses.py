"""Every object's box in the current LiDAR frame, vectorized (one pass per frame)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from world_model.geometry import BOX_CORNER_SIGNS
from world_model.scene import SceneFrame


@dataclass(frozen=True)
class ObjectPoses:
    """Shapes: N objects. Same values as ``SceneFrame.object_boxes_lidar`` / ``object_corners_lidar``."""

    centre: np.ndarray  # (N, 3) box centres, LiDAR frame
    yaw: np.ndarray  # (N,) yaw relative to the ego
    half: np.ndarray  # (N, 3) half length, width, height
    corners: np.ndarray  # (N, 8, 3) in the documented corner order

    @property
    def cos(self) -> np.ndarray:
        return np.cos(self.yaw)

    @property
    def sin(self) -> np.ndarray:
        return np.sin(self.yaw)


def object_poses(frame: SceneFrame, mount_height: float) -> ObjectPoses:
    """Boxes relative to a LiDAR ``mount_height`` above the ego's road point."""
    n = len(frame.objects)
    if n == 0:
        z = np.zeros((0, 3))
        return ObjectPoses(z, np.zeros(0), z, np.zeros((0, 8, 3)))
    world = np.array([o.box.center for o in frame.objects], dtype=np.float64)
    half = 0.5 * np.array([o.box.size for o in frame.objects], dtype=np.float64)
    if not (np.isfinite(world).all() and np.isfinite(half).all()):
        raise ValueError("object boxes must have finite centres and sizes")
    if (half <= 0).any():
        bad = frame.objects[int(np.nonzero((half <= 0).any(1))[0][0])]
        raise ValueError(f"object {bad.track_id!r} has a non-positive size {bad.box.size}")
    ego = frame.ego
    ce, se = math.cos(ego.yaw), math.sin(ego.yaw)
    dx, dy = world[:, 0] - ego.x, world[:, 1] - ego.y
    centre = np.stack([ce * dx + se * dy, -se * dx + ce * dy, world[:, 2] - mount_height], 1)
    yaw = (np.array([o.box.yaw for o in frame.objects]) - ego.yaw + np.pi) % (2 * np.pi) - np.pi
    c, s = np.cos(yaw), np.sin(yaw)
    local = BOX_CORNER_SIGNS[None] * half[:, None, :]  # (N, 8, 3)
    corners = (
        np.stack(
            [
                c[:, None] * local[..., 0] - s[:, None] * local[..., 1],
                s[:, None] * local[..., 0] + c[:, None] * local[..., 1],
                local[..., 2],
            ],
            -1,
        )
        + centre[:, None, :]
    )
    return ObjectPoses(centre=centre, yaw=yaw, half=half, corners=corners)
