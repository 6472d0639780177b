"""Frame conventions and small geometry helpers shared by every part of the project.

Conventions (DESIGN.md, "Conventions"):

* World, ego and LiDAR frames are right-handed: **x forward, y left, z up**, metres; yaw is
  counter-clockwise about +z, 0 along +x.
* The LiDAR frame is the reference sensor frame (paper §3.2): it sits above the ego origin at
  ``LidarSpec.mount_height`` with the ego's heading, so a point on the road has z = -mount_height.
* Inside a camera: OpenCV axes, x right, y down, z forward (the optical axis).
* Box corners: 8 corners in nuscenes-devkit's ``Box.corners()`` order. With l/w/h the length
  (along the box's own x), width (own y) and height, the corner offsets are::

      index:   0     1     2     3     4     5     6     7
      x:     +l/2  +l/2  +l/2  +l/2  -l/2  -l/2  -l/2  -l/2     (0-3 = front face)
      y:     +w/2  -w/2  -w/2  +w/2  +w/2  -w/2  -w/2  +w/2     (+y = the box's left)
      z:     +h/2  +h/2  -h/2  -h/2  +h/2  +h/2  -h/2  -h/2     (first two of each face on top)

  The box centre is the **geometric centre** (not the bottom face): an object standing on the
  road has centre z = height / 2 in the world frame. (MagicDrive's half-height bug came from
  mixing the two; tests pin this.)
"""

from __future__ import annotations

import numpy as np

# Unit corner offsets, multiplied by (l/2, w/2, h/2). Order documented in the module docstring.
BOX_CORNER_SIGNS = np.array(
    [
        [1, 1, 1],
        [1, -1, 1],
        [1, -1, -1],
        [1, 1, -1],
        [-1, 1, 1],
        [-1, -1, 1],
        [-1, -1, -1],
        [-1, 1, -1],
    ],
    dtype=np.float64,
)

# The 12 edges and 6 faces of a box, as indices into the corner order above.
BOX_EDGES = (
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
)
BOX_FACES = {
    "front": (0, 1, 2, 3),
    "back": (5, 4, 7, 6),
    "left": (4, 0, 3, 7),
    "right": (1, 5, 6, 2),
    "top": (4, 5, 1, 0),
    "bottom": (3, 2, 6, 7),
}


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation about +z by ``yaw`` radians (counter-clockwise), shape (3, 3)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def box_corners(center: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    """Eight corners of a yawed box in the documented order.

    Args:
        center: (3,) geometric centre.
        size: (3,) length, width, height.
        yaw: heading about +z.
    Returns:
        (8, 3) corners in the same frame as ``center``.
    """
    half = 0.5 * np.asarray(size, dtype=np.float64)
    local = BOX_CORNER_SIGNS * half
    return local @ yaw_matrix(yaw).T + np.asarray(center, dtype=np.float64)


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def world_to_ego_xy(points_xy: np.ndarray, ego_xy: np.ndarray, ego_yaw: float) -> np.ndarray:
    """Express world (x, y) points in the ego frame. points_xy: (..., 2) -> (..., 2)."""
    c, s = np.cos(ego_yaw), np.sin(ego_yaw)
    d = np.asarray(points_xy, dtype=np.float64) - np.asarray(ego_xy, dtype=np.float64)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def world_to_highway(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """Our frame -> highway-env's frame (x forward, y to the driver's right, heading clockwise; the
    map is its own inverse)."""
    return float(x), float(-y), float(-yaw)
