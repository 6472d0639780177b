"""Per-camera semantic label maps: which class every pixel of the ground-truth views shows.

The simulator knows each pixel's source: the sky, the road plane's label texture (off-road ground,
road surface, painted markings and road edges) or an object's polygon after occlusion. Label maps
are rendered with the same geometry as the images, at any resolution (the rig's intrinsics are
scaled), so they also serve as per-view layout rasters at latent resolution.

The decoder's maps (:meth:`LabelRasterizer.maps`) carry a second plane beside the class ids: each
object pixel's paint, unlit, in one byte (:func:`encode_paint`), 0 elsewhere: the albedo of the face
it shows, the object's colour (``SceneObject.color``) on its body, its glass, tyres and lamps their
own. Light, weather and fog are left to the model. The class plane says which pixels are objects.
A third plane carries the road's and the off-road ground's surface variation (:func:`encode_surface`):
the low-frequency patches of the world-aligned texture that brighten or darken the asphalt and the
grass, so that the ground moves past the cameras as the ego drives over it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np

from world_model.scene import CATEGORIES, SceneFrame
from world_model.sensors import CameraRig
from world_model.sim import ground, objects
from world_model.sim.cache import LruCache
from world_model.sim.config import SimConfig
from world_model.sim.lighting import lighting_for
from world_model.sim.poses import object_poses
from world_model.sim.scene_mesh import build_scene_mesh, object_key
from world_model.sim.texture import MapTexture, labels_layout, surface_variation

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


def scaled_rig(rig: CameraRig, height: int, width: int) -> CameraRig:
    """``rig`` with every camera resampled to ``height`` x ``width`` pixels (same field of view)."""
    if height < 1 or width < 1:
        raise ValueError(f"label map size must be positive, got height={height}, width={width}")
    cams = []
    for cam in rig.cameras:
        k = cam.K.copy()
        k[0] *= width / cam.width
        k[1] *= height / cam.height
        cams.append(replace(cam, K=k, width=width, height=height))
    return CameraRig(cameras=tuple(cams))


def texture_classes(levels: int) -> np.ndarray:
    """(256,) uint8: the label class of every road-texture label."""
    off0, road0, marking, edge = labels_layout(levels)
    table = np.full(256, OFFROAD, dtype=np.uint8)
    table[road0 : road0 + levels] = ROAD
    table[[marking, edge]] = MARKING
    return table


def texture_surfaces(levels: int) -> np.ndarray:
    """(256,) uint8: the surface byte (:func:`encode_surface`) of every road-texture label; 0 for
    the markings and road edges, which are painted flat."""
    off0, road0, _marking, _edge = labels_layout(levels)
    table = np.zeros(256, dtype=np.uint8)
    for first in (off0, road0):
        table[first : first + levels] = encode_surface(surface_variation(levels))
    return table


class LabelRasterizer:
    """Renders label maps of frames; keeps, for the last ``keep`` of each, the ray geometry of a
    rig, the road texture of a map and the mesh of an object set (a rollout shares them across its
    frames, and one rasterizer may serve every rollout of a vector env)."""

    def __init__(self, config: SimConfig | None = None, keep: int = 64) -> None:
        self.config = config or SimConfig()
        self._classes = texture_classes(self.config.texture_noise_levels)
        self._surfaces = texture_surfaces(self.config.texture_noise_levels)
        self._rigs = LruCache(keep)
        self._textures = LruCache(keep)
        self._meshes = LruCache(keep)

    def _rig(self, rig: CameraRig, height: int, width: int, mount_height: float) -> _ScaledRig:
        def make() -> _ScaledRig:
            scaled = scaled_rig(rig, height, width)
            rays = ground.ground_rays(scaled, mount_height, self.config.max_ground_distance_m)
            return _ScaledRig(scaled, objects.rig_arrays(scaled), rays)

        return self._rigs.get((id(rig), height, width, mount_height), (rig,), make)

    def __call__(self, frame: SceneFrame, rig: CameraRig, height: int, width: int) -> np.ndarray:
        """(V, H, W) uint8 class ids (:data:`LABEL_CLASSES`) of ``frame`` seen by ``rig`` at H x W."""
        return self.maps(frame, rig, height, width)[:, CLASS_PLANE]

    def maps(self, frame: SceneFrame, rig: CameraRig, height: int, width: int) -> np.ndarray:
        """(V, :data:`MAP_PLANES`, H, W) uint8: the class ids of ``frame`` seen by ``rig`` at H x W,
        the paint of every object pixel (:func:`encode_paint` of its face's albedo; 0 elsewhere) and
        the surface of every road and off-road pixel (:func:`encode_surface`; 0 elsewhere)."""
        cfg = self.config
        small = self._rig(rig, height, width, frame.lidar.mount_height)
        texture = self._textures.get(frame.map.digest, (), lambda: MapTexture(frame.map, cfg))
        texels = texture.lookup_ego(small.rays.ground_xy, frame.ego.x, frame.ego.y, frame.ego.yaw)
        out = np.zeros((small.rig.num_views, MAP_PLANES, height, width), dtype=np.uint8)
        for plane, table, sky in ((CLASS_PLANE, self._classes, SKY), (SURFACE_PLANE, self._surfaces, 0)):
            flat = np.full(small.rays.distance.size, sky, dtype=np.uint8)
            flat[small.rays.ground_index] = table[texels]
            out[:, plane] = flat.reshape(small.rig.num_views, height, width)
        if frame.objects:
            plan = objects.plan_objects(
                frame,
                self._meshes.get(object_key(frame), (), lambda: build_scene_mesh(frame)),
                object_poses(frame, frame.lidar.mount_height),
                small.rig,
                small.arrays,
                lighting_for(frame.prompt),
                cfg.near_plane_m,
                cfg.min_face_area_px,
                cfg.impostor_max_px,
                cfg.subpixel_bits,
            )
            unlit = replace(plan, colors=np.clip(plan.albedos, 0.0, 255.0))
            ids = np.zeros((height, width), dtype=np.int32)
            albedo = np.zeros((height, width, 3), dtype=np.uint8)
            lut = np.array([0] + [CATEGORY_CLASS[o.category] for o in frame.objects], dtype=np.uint8)
            for v in range(small.rig.num_views):
                ids[:] = 0
                objects.paint(ids, plan, v, False, cfg.subpixel_bits, value=lambda o: o + 1)
                objects.paint(albedo, unlit, v, False, cfg.subpixel_bits)
                seen = ids > 0
                out[v, CLASS_PLANE][seen] = lut[ids[seen]]
                out[v, PAINT_PLANE][seen] = encode_paint(albedo[seen])
                out[v, SURFACE_PLANE][seen] = 0
        return out


class _ScaledRig(NamedTuple):
    """A rig resampled to a label map's size, its arrays for the painter and its ground rays."""

    rig: CameraRig
    arrays: objects.RigArrays
    rays: ground.GroundRays


def label_maps(
    frame: SceneFrame, rig: CameraRig, height: int, width: int, config: SimConfig | None = None
) -> np.ndarray:
    """(V, H, W) uint8 class ids (:data:`LABEL_CLASSES`) of every camera of ``rig`` at H x W pixels.

    For many frames of one rollout, keep one :class:`LabelRasterizer` instead (it reuses the ray
    geometry and road texture).
    """
    return LabelRasterizer(config)(frame, rig, height, width)
