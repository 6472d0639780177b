"""Rain streaks and snow flakes: a pool of overlay layers per resolution, picked per frame.

Drawing hundreds of streaks every frame would cost more than the rest of the image, so a few
larger-than-image alpha layers are drawn once; each frame picks a layer and an offset per view
from a seed derived from the frame (scenario name and frame index), which keeps rendering a pure,
deterministic function of the frame while the streaks move from frame to frame. The world model
blends the same windows over its decoded cameras (:func:`world_model.raster.maps.camera_precipitation`):
the streaks of a frame are nothing its latents could hold.
"""

from __future__ import annotations

import math
import zlib

import cv2
import numpy as np

from world_model.scene import SceneFrame
from world_model.sim.config import SimConfig
from world_model.sim.lighting import Lighting

# Streak length as a fraction of the image height, slant from vertical (radians), alpha range.
RAIN_LENGTH_FRAC = (0.06, 0.16)
RAIN_SLANT_RAD = (0.12, 0.3)
RAIN_ALPHA = (0.25, 0.55)
# Flake radius as a fraction of the image height, alpha range.
SNOW_RADIUS_FRAC = (0.003, 0.009)
SNOW_ALPHA = (0.6, 0.95)


def frame_seed(frame: SceneFrame) -> int:
    """A stable 32-bit seed from the frame (Python's ``hash`` of a str changes between runs)."""
    return zlib.crc32(f"{frame.scenario}|{frame.frame_index}".encode())


def precipitation_layers(kind: str, h: int, w: int, config: SimConfig) -> np.ndarray:
    """(layers, 2h, 2w) uint8 alpha (255 = opaque) for "rain" or "snow"."""
    if kind not in ("rain", "snow"):
        raise ValueError(f"precipitation kind must be 'rain' or 'snow', got {kind!r}")
    rng = np.random.default_rng(config.precipitation_seed)
    hh, ww = 2 * h, 2 * w
    per_kpx = config.rain_streaks_per_kpx if kind == "rain" else config.snow_flakes_per_kpx
    count = max(1, round(per_kpx * hh * ww / 1000.0))
    shift = config.subpixel_bits
    scale = 1 << shift
    layers = np.zeros((config.precipitation_layers, hh, ww), dtype=np.uint8)
    for layer in layers:
        xs, ys = rng.random(count) * ww, rng.random(count) * hh
        if kind == "rain":
            lengths = rng.uniform(*RAIN_LENGTH_FRAC, count) * h
            slants = rng.uniform(*RAIN_SLANT_RAD, count)
            alphas = rng.uniform(*RAIN_ALPHA, count)
            for x, y, ln, sl, a in zip(xs, ys, lengths, slants, alphas, strict=True):
                p0 = (round(x * scale), round(y * scale))
                p1 = (round((x + ln * math.sin(sl)) * scale), round((y + ln * math.cos(sl)) * scale))
                cv2.line(layer, p0, p1, int(255 * a), 1, cv2.LINE_AA, shift)
        else:
            radii = rng.uniform(*SNOW_RADIUS_FRAC, count) * h
            alphas = rng.uniform(*SNOW_ALPHA, count)
            for x, y, r, a in zip(xs, ys, radii, alphas, strict=True):
                centre = (round(x * scale), round(y * scale))
                cv2.circle(layer, centre, max(1, round(r * scale)), int(255 * a), -1, cv2.LINE_AA, shift)
    return layers


def precipitation_rgb(lighting: Lighting) -> np.ndarray:
    """(3,) uint8: the colour ``lighting``'s streaks or flakes are blended in."""
    return np.clip(np.round(lighting.precipitation_color), 0, 255).astype(np.uint8)


def blend(images: np.ndarray, alpha: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """``images`` (N, W, 3) uint8 with ``rgb`` (3,) uint8 blended over them by ``alpha`` (N, W)
    uint8 (255 = opaque): the simulator's cameras and the world model's decoded ones alike."""
    weight = alpha.astype(np.float32) / 255.0
    solid = np.empty_like(images)
    solid[:] = rgb
    return cv2.blendLinear(images, solid, 1.0 - weight, weight)


class Overlay:
    """Rain or snow for one image size: the pool of alpha layers, drawn once, and each frame's
    window of it."""

    def __init__(self, kind: str, h: int, w: int, config: SimConfig) -> None:
        self.layers = precipitation_layers(kind, h, w, config)
        self.h, self.w = h, w

    def alpha(self, frame: SceneFrame, views: int) -> np.ndarray:
        """(views * H, W) uint8: ``frame``'s streaks over its ``views`` stacked views, one random
        window of a random layer per view, drawn from a seed derived from the frame."""
        rng = np.random.default_rng(frame_seed(frame))
        picks = rng.integers(0, len(self.layers), views)
        oy, ox = rng.integers(0, self.h, views), rng.integers(0, self.w, views)
        h, w = self.h, self.w
        return np.concatenate([self.layers[k, y : y + h, x : x + w] for k, y, x in zip(picks, oy, ox, strict=True)])
