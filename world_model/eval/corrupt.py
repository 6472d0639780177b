"""Image corruptions: negatives for the judge's clarity head, and corrupted-Oracle rows that a
sound evaluation must score below the Oracle. All take and return uint8 (..., H, W, 3)."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np


def _per_image(images: np.ndarray, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    if images.dtype != np.uint8 or images.ndim < 3 or images.shape[-1] != 3:
        raise ValueError(f"images must be uint8 (..., H, W, 3), got {images.dtype} {images.shape}")
    flat = images.reshape(-1, *images.shape[-3:])
    return np.stack([fn(img) for img in flat]).reshape(images.shape)


def blur(images: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of standard deviation ``sigma`` pixels."""
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    return _per_image(images, lambda im: cv2.GaussianBlur(im, (0, 0), sigma, borderType=cv2.BORDER_REFLECT))


def add_noise(images: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """Additive Gaussian noise of standard deviation ``std`` (0-255 scale), clipped."""
    noisy = images.astype(np.float32) + rng.normal(0.0, std, images.shape).astype(np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def pixelate(images: np.ndarray, factor: int) -> np.ndarray:
    """Downsample by ``factor`` (area) and upsample back (nearest): blocky detail loss."""
    if factor < 2:
        raise ValueError(f"factor must be >= 2, got {factor}")

    def one(im: np.ndarray) -> np.ndarray:
        h, w = im.shape[:2]
        small = cv2.resize(im, (max(1, w // factor), max(1, h // factor)), interpolation=cv2.INTER_AREA)
        return cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)

    return _per_image(images, one)


def color_shift(images: np.ndarray, shift: int = 2) -> np.ndarray:
    """Rotate the RGB channels by ``shift`` (1: RGB -> BRG): colours change, structure does not."""
    if images.dtype != np.uint8 or images.shape[-1] != 3:
        raise ValueError(f"images must be uint8 (..., 3), got {images.dtype} {images.shape}")
    return np.ascontiguousarray(np.roll(images, shift, axis=-1))
