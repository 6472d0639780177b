"""Per-camera semantic label maps: which class every pixel of the ground-truth views shows.

The classes (:data:`LABEL_CLASSES`), planes and byte codes (:func:`encode_paint`,
:func:`encode_surface`) of a map are named in :mod:`world_model.raster.classes`; this module draws
them.

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

from world_model.raster.classes import (
    CATEGORY_CLASS,
    CLASS_PLANE,
    MAP_PLANES,
    MARKING,
    OFFROAD,
    PAINT_PLANE,
    ROAD,
    SKY,
    SURFACE_PLANE,
    encode_paint,
    encode_surface,
)
from world_model.scene import SceneFrame
from world_model.sensors import CameraRig
from world_model.sim import ground, objects
from world_model.sim.cache import LruCache
from world_model.sim.config import SimConfig
from world_model.sim.lighting import lighting_for
from world_model.sim.poses import object_poses
from world_model.sim.scene_mesh import build_scene_mesh, object_key
from world_model.sim.texture import MapTexture, labels_layout, surface_variation


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
                cfg,
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
