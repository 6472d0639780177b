"""The label maps' vocabulary: class ids, planes, and the paint and surface bytes.

A decoder's label map of one camera is (:data:`MAP_PLANES`, H, W) uint8: the class id of every
pixel (:data:`LABEL_CLASSES`), the unlit paint of every object pixel (:func:`encode_paint`) and the
surface variation of every road and off-road pixel (:func:`encode_surface`). This module only names
them (numpy, no renderer), so that the model's config and its decoder read them without the
procedural simulator that draws them (:class:`~world_model.sim.labels.LabelRasterizer`).
"""

from __future__ import annotations

import numpy as np

from world_model.scene import CATEGORIES

# Class ids are the index in this table; a label map is (V, H, W) uint8 of these ids.
LABEL_CLASSES: tuple[str, ...] = (
    "sky",
    "offroad",
    "road",
    "marking",  # painted lane markings and road-edge lines
    "vehicle",
    "vulnerable",  # pedestrians and cyclists
    "other_object",  # cones, barriers
)
SKY, OFFROAD, ROAD, MARKING, VEHICLE, VULNERABLE, OTHER_OBJECT = range(len(LABEL_CLASSES))
# The classes whose look the scene's weather and light decide (the first ids): the rest are objects,
# whose look is their own.
SCENE_LOOK_CLASSES = (SKY, OFFROAD, ROAD, MARKING)
assert tuple(range(len(SCENE_LOOK_CLASSES))) == SCENE_LOOK_CLASSES
# An id that draws nothing (the decoder's all-zero one-hot): the LiDAR view, which has no label
# map, and frames that will not be decoded.
NO_LABEL = 255
# The planes of a decoder's label map (V, 3, H, W): class ids, the objects' paint, the ground's surface.
CLASS_PLANE, PAINT_PLANE, SURFACE_PLANE = 0, 1, 2
MAP_PLANES = 3
# Surface bytes: 0 where no textured surface shows (sky, markings, objects), else 1 + the
# variation's place in [-1, 1] on SURFACE_STEPS steps.
SURFACE_STEPS = 254
# Bits of red, green and blue in a paint byte (8-bit truecolour, RRRGGGBB): eight levels of red
# and green, four of blue; enough to tell a red car from a dark red, navy or blue one.
PAINT_BITS = (3, 3, 2)
PAINT_CHANNELS = len(PAINT_BITS)  # the decoder reads paint as RGB

CATEGORY_CLASS: dict[str, int] = {
    "car": VEHICLE,
    "truck": VEHICLE,
    "bus": VEHICLE,
    "van": VEHICLE,
    "motorcycle": VEHICLE,
    "tree_truck": VEHICLE,
    "cement_mixer": VEHICLE,
    "cyclist": VULNERABLE,
    "pedestrian": VULNERABLE,
    "cone": OTHER_OBJECT,
    "barrier": OTHER_OBJECT,
}
assert set(CATEGORY_CLASS) == set(CATEGORIES), "every scene category needs a label class"


def encode_paint(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 RGB -> (...) uint8 paint bytes (:data:`PAINT_BITS`, the high bits of each)."""
    rgb = np.asarray(rgb, dtype=np.uint8)
    out = np.zeros(rgb.shape[:-1], dtype=np.uint8)
    for c, bits in enumerate(PAINT_BITS):
        out = (out << bits) | (rgb[..., c] >> (8 - bits))
    return out


def encode_surface(variation: np.ndarray) -> np.ndarray:
    """(...) float variation in [-1, 1] (:func:`~world_model.sim.texture.surface_variation`) -> (...)
    uint8 surface bytes, 1 to 255 (0 is kept for "no textured surface")."""
    v = np.clip(np.asarray(variation, dtype=np.float64), -1.0, 1.0)
    return (1 + np.rint((v + 1.0) * SURFACE_STEPS / 2)).astype(np.uint8)


def decode_surface(surface: np.ndarray) -> np.ndarray:
    """(...) uint8 surface bytes -> (...) float32 variation in [-1, 1], 0 where the byte is 0."""
    surface = np.asarray(surface, dtype=np.uint8)
    v = (surface.astype(np.float32) - 1.0) * (2.0 / SURFACE_STEPS) - 1.0
    return np.where(surface > 0, v, 0.0).astype(np.float32)


def blank_maps(leading: tuple[int, ...], height: int, width: int) -> np.ndarray:
    """(*leading, :data:`MAP_PLANES`, H, W) uint8 label maps that draw nothing: classes
    :data:`NO_LABEL`, no paint, no surface (the LiDAR view's, and frames that will not be decoded)."""
    out = np.zeros((*leading, MAP_PLANES, height, width), dtype=np.uint8)
    out[..., CLASS_PLANE, :, :] = NO_LABEL
    return out


def decode_paint(paint: np.ndarray) -> np.ndarray:
    """(...) uint8 paint bytes -> (..., 3) float32 RGB in [0, 1], each channel's levels spread evenly."""
    paint = np.asarray(paint, dtype=np.uint8)
    channels, shift = [], 8
    for bits in PAINT_BITS:
        shift -= bits
        channels.append(((paint >> shift) & ((1 << bits) - 1)).astype(np.float32) / ((1 << bits) - 1))
    return np.stack(channels, axis=-1)
