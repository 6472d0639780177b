"""The sensor observation every backend returns (procedural simulator or world model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorSelection:
    """Which sensors a world model decodes: decoding a view costs a decoder pass per frame, so an
    env decodes only the sensors it observes or renders. A sensor left out is ``None`` in the
    :class:`Observation`, never an array of zeros that could pass for a reading."""

    cameras: bool = True
    lidar: bool = True


ALL_SENSORS = SensorSelection()
SENSOR_NAMES = ("cameras", "lidar")  # the sensors a world model decodes, as Observation and SensorSelection name them


class SensorNotDecoded(RuntimeError):
    """A sensor was read from an observation whose world model did not decode it."""


@dataclass
class Observation:
    """Synchronized sensors at one tick.

    cameras: uint8 (V, H, W, 3), views in the rig's order; None when not decoded.
    lidar: float32 (beams, azimuth) range map in metres, ``LidarSpec.no_return`` where no return;
    None when not decoded (:class:`SensorSelection`).
    bev: optional uint8 {0,1} (h, w, c) map raster around the ego (``BevSpec``).
    """

    cameras: np.ndarray | None
    lidar: np.ndarray | None
    bev: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.cameras is not None and (
            self.cameras.dtype != np.uint8 or self.cameras.ndim != 4 or self.cameras.shape[-1] != 3
        ):
            raise ValueError(f"cameras must be uint8 (V, H, W, 3), got {self.cameras.dtype} {self.cameras.shape}")
        if self.lidar is not None and (self.lidar.dtype != np.float32 or self.lidar.ndim != 2):
            raise ValueError(f"lidar must be float32 (beams, azimuth), got {self.lidar.dtype} {self.lidar.shape}")

    def copy(self) -> Observation:
        """An observation with its own copies of the arrays."""
        return Observation(*(None if a is None else a.copy() for a in (self.cameras, self.lidar, self.bev)))

    def sensor(self, name: str) -> np.ndarray:
        """The ``"cameras"`` or ``"lidar"`` array; a :class:`SensorNotDecoded` error when that
        sensor was not decoded (read it only where its :class:`SensorSelection` holds it)."""
        if name not in SENSOR_NAMES:
            raise ValueError(f"sensor must be one of {SENSOR_NAMES}, got {name!r}")
        value = getattr(self, name)
        if value is None:
            raise SensorNotDecoded(
                f"this observation has no {name}: the world model did not decode them (an env decodes only "
                "the sensors in its observation_keys, and both when it renders)"
            )
        return value
