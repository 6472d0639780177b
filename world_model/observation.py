"""The sensor observation every backend returns (procedural simulator or world model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Observation:
    """Synchronized sensors at one tick.

    cameras: uint8 (V, H, W, 3), views in the rig's order.
    lidar: float32 (beams, azimuth) range map in metres, ``LidarSpec.no_return`` where no return.
    bev: optional uint8 {0,1} (h, w, c) map raster around the ego (``BevSpec``).
    """

    cameras: np.ndarray
    lidar: np.ndarray
    bev: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.cameras.dtype != np.uint8 or self.cameras.ndim != 4 or self.cameras.shape[-1] != 3:
            raise ValueError(f"cameras must be uint8 (V, H, W, 3), got {self.cameras.dtype} {self.cameras.shape}")
        if self.lidar.dtype != np.float32 or self.lidar.ndim != 2:
            raise ValueError(f"lidar must be float32 (beams, azimuth), got {self.lidar.dtype} {self.lidar.shape}")
