"""Perturbed policies: a zoo policy whose sensors or actuators are degraded.

Each wraps another :class:`~m4world_env.zoo.base.SensorPolicy` and changes what it sees (Gaussian
range noise and dropped returns on the LiDAR, pixel noise on the cameras, a view blacked out) or
when its command arrives (a delay of whole policy steps). The noise is seeded per episode.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import numpy as np

from m4world_env.zoo.base import EgoStatus, SensorPolicy


class Perturbed(SensorPolicy):
    """``inner`` driving from degraded sensors, with its commands ``delay_steps`` steps late.

    ``lidar_noise_m``: std of the range noise; ``lidar_dropout``: share of returns lost (read as no
    return); ``camera_noise``: std of the pixel noise in grey levels; ``blind_views``: cameras seen
    black; ``blind_lidar_deg``: an azimuth interval ``(low, high)`` (deg, + left) with no returns.
    """

    def __init__(
        self,
        inner: SensorPolicy,
        rng: np.random.Generator,
        *,
        lidar_noise_m: float = 0.0,
        lidar_dropout: float = 0.0,
        camera_noise: float = 0.0,
        blind_views: tuple[str, ...] = (),
        blind_lidar_deg: tuple[float, float] | None = None,
        delay_steps: int = 0,
    ) -> None:
        super().__init__(inner.geometry)
        self.inner, self.rng = inner, rng
        self.lidar_noise_m, self.lidar_dropout, self.camera_noise = lidar_noise_m, lidar_dropout, camera_noise
        self._blind = [inner.geometry.view_index(v) for v in blind_views]
        self._blind_columns = None
        if blind_lidar_deg is not None:
            az = np.rad2deg(inner.geometry.lidar.azimuths())
            self._blind_columns = (az >= blind_lidar_deg[0]) & (az <= blind_lidar_deg[1])
        self._queue: deque[np.ndarray] = deque()
        self.delay_steps = delay_steps

    def drive(self, obs: Mapping[str, np.ndarray], status: EgoStatus) -> np.ndarray:
        action = self.inner.drive(self.degrade(obs), status)
        if not self.delay_steps:
            return action
        self._queue.append(action)
        if len(self._queue) <= self.delay_steps:  # nothing has arrived yet: coast
            return self.geometry.action(0.0, 0.0)
        return self._queue.popleft()

    def degrade(self, obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``obs`` as the degraded sensors show it (a new dict; the env's arrays are not changed)."""
        out = dict(obs)
        spec = self.geometry.lidar
        if "lidar" in obs and (self.lidar_noise_m or self.lidar_dropout or self._blind_columns is not None):
            ranges = obs["lidar"].astype(np.float32, copy=True)
            hit = ranges > spec.no_return
            if self.lidar_noise_m:
                noisy = ranges + self.rng.normal(0.0, self.lidar_noise_m, ranges.shape).astype(np.float32)
                ranges = np.where(hit, np.clip(noisy, 0.1, spec.max_range), ranges)
            if self.lidar_dropout:
                ranges[self.rng.random(ranges.shape) < self.lidar_dropout] = spec.no_return
            if self._blind_columns is not None:
                ranges[:, self._blind_columns] = spec.no_return
            out["lidar"] = ranges
        if "cameras" in obs and (self.camera_noise or self._blind):
            cams = obs["cameras"].astype(np.float32)
            if self.camera_noise:
                cams += self.rng.normal(0.0, self.camera_noise, cams.shape).astype(np.float32)
            cams[self._blind] = 0.0
            out["cameras"] = np.clip(cams, 0, 255).astype(np.uint8)
        return out
