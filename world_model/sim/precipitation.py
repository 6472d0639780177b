"""Rain streaks and snow flakes: a pool of overlay layers per resolution, picked per frame.

Drawing hundreds of streaks every frame would cost more than the rest of the image, so a few
larger-than-image alpha layers are drawn once; each frame picks a layer and an offset per view
from a seed derived from the frame (scenario name and frame index), which keeps rendering a pure,
deterministic function of the frame while the streaks move from frame to frame.
"""

from __future__ import annotations

import math
import zlib

import cv2
import numpy as np

from world_model.scene import SceneFrame
from world_model.sim.config import SimConfig

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
    """(layers, 2h, 2w) float32 alpha in [0, 1] for "rain" or "snow"."""
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
    return layers.astype(np.float32) / 255.0


class Overlay:
    """Rain or snow for one image size: the layer pool plus what blending needs, prepared once."""

    def __init__(self, kind: str, views: int, h: int, w: int, color: np.ndarray, config: SimConfig) -> None:
        self.alpha = precipitation_layers(kind, h, w, config)
        self.keep = 1.0 - self.alpha
        self.views, self.h, self.w = views, h, w
        self.solid = np.empty((views * h, w, 3), dtype=np.uint8)
        self.solid[:] = np.clip(np.round(color), 0, 255).astype(np.uint8)

    def apply(self, images: np.ndarray, frame: SceneFrame) -> np.ndarray:
        """Blend this frame's streaks over ``images`` (V*H, W, 3) uint8: one random window of a
        random layer per view, drawn from a seed derived from the frame."""
        rng = np.random.default_rng(frame_seed(frame))
        picks = rng.integers(0, len(self.alpha), self.views)
        oy, ox = rng.integers(0, self.h, self.views), rng.integers(0, self.w, self.views)
        windows = list(zip(picks, oy, ox, strict=True))
        h, w = self.h, self.w
        alpha = np.concatenate([self.alpha[k, y : y + h, x : x + w] for k, y, x in windows])
        keep = np.concatenate([self.keep[k, y : y + h, x : x + w] for k, y, x in windows])
        return cv2.blendLinear(images, self.solid, keep, alpha)
