"""Wrappers: observations for RL libraries (Stable-Baselines3's ``MultiInputPolicy`` in particular),
and :class:`RecordVideo` with every sensor frame.

SB3 treats a uint8 (H, W, C) Box as an image and a float Box as a vector. The env's native
``cameras`` (V, H, W, 3) and ``lidar`` (beams, 1024) are neither, so :class:`SB3Observations`
stacks the views on channels (H, W, 3V) and min-pools the LiDAR azimuth to a short vector
(the nearest return per sector matters for driving; 0.0 "no return" is treated as far).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class SB3Observations(gym.ObservationWrapper):
    """cameras (V,H,W,3) → (H,W,3V) uint8; lidar (B,A) → (B * sectors,) float32 nearest range per sector."""

    def __init__(self, env: gym.Env, lidar_sectors: int = 32) -> None:
        super().__init__(env)
        src = env.observation_space
        self.lidar_sectors = lidar_sectors
        out = {}
        for key, space in src.spaces.items():
            if key == "cameras":
                v, h, w, c = space.shape
                out[key] = spaces.Box(0, 255, shape=(h, w, v * c), dtype=np.uint8)
            elif key == "lidar":
                beams, azimuth = space.shape
                if azimuth % lidar_sectors:
                    raise ValueError(f"lidar_sectors={lidar_sectors} must divide the azimuth resolution {azimuth}")
                self._max_range = float(space.high.max())
                out[key] = spaces.Box(0.0, self._max_range, shape=(beams * lidar_sectors,), dtype=np.float32)
            elif key == "state":
                out[key] = spaces.Box(space.low.reshape(-1), space.high.reshape(-1), dtype=np.float32)
            else:
                out[key] = space
        self.observation_space = spaces.Dict(out)

    def observation(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = dict(obs)
        if "cameras" in obs:
            cams = obs["cameras"]
            out["cameras"] = np.ascontiguousarray(cams.transpose(1, 2, 0, 3).reshape(cams.shape[1], cams.shape[2], -1))
        if "lidar" in obs:
            ranges = np.where(obs["lidar"] > 0, obs["lidar"], self._max_range)
            beams, azimuth = ranges.shape
            pooled = ranges.reshape(beams, self.lidar_sectors, azimuth // self.lidar_sectors).min(axis=2)
            out["lidar"] = pooled.reshape(-1).astype(np.float32)
        if "state" in obs:
            out["state"] = obs["state"].reshape(-1)
        return out


class RecordVideo(gym.wrappers.RecordVideo):
    """gymnasium's ``RecordVideo`` keeping every frame ``render()`` returns: with
    ``render_mode="rgb_array_list"`` a step's video gets each of its sensor frames (at the env's
    ``render_fps`` = sensor frequency), where gymnasium's own keeps the last one of each step.
    Needs moviepy (the ``video`` extra), like gymnasium's."""

    def _capture_frame(self) -> None:
        if self.env.render_mode != "rgb_array_list":
            super()._capture_frame()
            return
        frames = self.env.render()
        self.render_history += frames
        self.recorded_frames += frames
