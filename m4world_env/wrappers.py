"""Wrappers: observations for RL libraries (Stable-Baselines3's ``MultiInputPolicy`` in particular),
and :class:`RecordVideo` with every sensor frame.

SB3 treats a uint8 (H, W, C) Box as an image and a float Box as a vector. The env's native
``cameras`` (V, H, W, 3) and ``lidar`` (beams, 1024) are neither, so :class:`SB3Observations`
stacks the views on channels (H, W, 3V) and min-pools the LiDAR azimuth to a short vector
(the nearest return per sector matters for driving; 0.0 "no return" is treated as far).
:class:`SB3ObservationMap` is that mapping alone, for a vector env's rows (:mod:`m4world_env.sb3`).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class SB3ObservationMap:
    """One env's observations for SB3: cameras (V,H,W,3) → (H,W,3V) uint8; lidar (B,A) → (B * sectors,)
    float32 nearest range per sector; state flattened. :attr:`space` is the mapped observation space."""

    def __init__(self, space: spaces.Dict, lidar_sectors: int = 32) -> None:
        self.lidar_sectors = lidar_sectors
        out = {}
        for key, sub in space.spaces.items():
            if key == "cameras":
                v, h, w, c = sub.shape
                out[key] = spaces.Box(0, 255, shape=(h, w, v * c), dtype=np.uint8)
            elif key == "lidar":
                beams, azimuth = sub.shape
                if azimuth % lidar_sectors:
                    raise ValueError(f"lidar_sectors={lidar_sectors} must divide the azimuth resolution {azimuth}")
                self._max_range = float(sub.high.max())
                out[key] = spaces.Box(0.0, self._max_range, shape=(beams * lidar_sectors,), dtype=np.float32)
            elif key == "state":
                out[key] = spaces.Box(sub.low.reshape(-1), sub.high.reshape(-1), dtype=np.float32)
            else:
                out[key] = sub
        self.space = spaces.Dict(out)

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
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


class SB3Observations(gym.ObservationWrapper):
    """A single env with :class:`SB3ObservationMap`'s observations."""

    def __init__(self, env: gym.Env, lidar_sectors: int = 32) -> None:
        super().__init__(env)
        self.observation_map = SB3ObservationMap(env.observation_space, lidar_sectors)
        self.observation_space = self.observation_map.space

    def observation(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return self.observation_map(obs)


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
