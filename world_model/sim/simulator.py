"""The procedural sensor simulator: a :class:`SceneFrame` in, ground-truth sensors out.

Rendering is a pure function of the frame. Per-rig, per-LiDAR and per-map precomputations are
cached, keyed by the identity of those objects (a rollout shares one map / rig / spec object
across its frames), and per object set by value.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from world_model.observation import Observation
from world_model.scene import SceneFrame
from world_model.sensors import BevSpec, CameraRig, CameraSpec, LidarSpec
from world_model.sim import ground, lidar, objects, precipitation
from world_model.sim.cache import LruCache
from world_model.sim.config import SimConfig
from world_model.sim.lighting import SKY_DISTANCE_M, SKY_GRADIENT_SPAN_RAD, lighting_for
from world_model.sim.poses import ObjectPoses, object_poses
from world_model.sim.scene_mesh import SceneMesh, build_scene_mesh, object_key
from world_model.sim.texture import MapTexture, palette


def _check_rig(rig: CameraRig) -> None:
    if rig.num_views < 1:
        raise ValueError("the camera rig has no cameras")
    sizes = {(c.height, c.width) for c in rig.cameras}
    if len(sizes) != 1:
        raise ValueError(f"all cameras of a rig must share one resolution, got {sorted(sizes)}")
    h, w = sizes.pop()
    if h < 1 or w < 1:
        raise ValueError(f"camera resolution must be positive, got {h}x{w}")


class ProceduralSimulator:
    """Renders cameras (V, H, W, 3) uint8, a LiDAR range map (beams, azimuth) float32 metres and a
    BEV raster (h, w, c) {0, 1} uint8 from a :class:`SceneFrame`.

    ``rig`` / ``lidar`` / ``bev`` override the frame's own specs when given.
    """

    def __init__(
        self,
        rig: CameraRig | None = None,
        lidar: LidarSpec | None = None,
        bev: BevSpec | None = None,
        config: SimConfig | None = None,
    ) -> None:
        if rig is not None:
            _check_rig(rig)
        self.rig, self.lidar, self.bev = rig, lidar, bev
        self.config = config or SimConfig()
        n = self.config.cache_size
        self._textures = LruCache(self.config.texture_cache_size)
        self._rays = LruCache(n)
        self._shading = LruCache(n)
        self._lidar_rays = LruCache(n)
        self._rig_arrays = LruCache(n)
        self._meshes = LruCache(n)
        self._precip = LruCache(n)
        self._poses = LruCache(1)  # render() asks for the same frame's poses twice

    # -- specs and caches ---------------------------------------------------------------------

    def _specs(self, frame: SceneFrame) -> tuple[CameraRig, LidarSpec, BevSpec]:
        if not isinstance(frame, SceneFrame):
            raise TypeError(f"expected a SceneFrame, got {type(frame).__name__}")
        ego = frame.ego
        if not all(math.isfinite(v) for v in (ego.x, ego.y, ego.yaw)):
            raise ValueError(f"ego pose must be finite, got x={ego.x}, y={ego.y}, yaw={ego.yaw}")
        rig = self.rig if self.rig is not None else frame.rig
        if self.rig is None:
            _check_rig(rig)
        return (
            rig,
            self.lidar if self.lidar is not None else frame.lidar,
            self.bev if self.bev is not None else frame.bev,
        )

    def _object_poses(self, frame: SceneFrame, spec: LidarSpec) -> ObjectPoses:
        return self._poses.get((id(frame), spec.mount_height), (frame,), lambda: object_poses(frame, spec.mount_height))

    def _scene_mesh(self, frame: SceneFrame) -> SceneMesh:
        return self._meshes.get(object_key(frame), (), lambda: build_scene_mesh(frame))

    def _plan(self, frame: SceneFrame, rig: CameraRig, spec: LidarSpec) -> objects.DrawPlan:
        cfg = self.config
        return objects.plan_objects(
            frame,
            self._scene_mesh(frame),
            self._object_poses(frame, spec),
            rig,
            self._rig_arrays.get(id(rig), (rig,), lambda: objects.rig_arrays(rig)),
            lighting_for(frame.prompt),
            cfg,
        )

    # -- sensors --------------------------------------------------------------------------------

    def render(self, frame: SceneFrame, with_bev: bool = True) -> Observation:
        """All sensors of ``frame``; ``bev`` is None when ``with_bev`` is False."""
        return Observation(
            cameras=self.render_cameras(frame),
            lidar=self.render_lidar(frame),
            bev=self.render_bev(frame) if with_bev else None,
        )

    def render_cameras(self, frame: SceneFrame) -> np.ndarray:
        """(V, H, W, 3) uint8 RGB images in the rig's view order."""
        rig, spec, _ = self._specs(frame)
        cfg = self.config
        h, w = rig.resolution
        lighting = lighting_for(frame.prompt)
        weather, tod = frame.prompt.weather, frame.prompt.time_of_day
        tex = self._textures.get(frame.map.digest, (), lambda: MapTexture(frame.map, cfg))
        rays = self._rays.get(
            (id(rig), spec.mount_height),
            (rig,),
            lambda: ground.ground_rays(rig, spec.mount_height, cfg.max_ground_distance_m),
        )

        def make_shading() -> ground.BackgroundShading:
            albedo = palette(lighting, cfg.texture_noise_levels)
            return ground.background_shading(
                rays, lighting, albedo, SKY_DISTANCE_M, SKY_GRADIENT_SPAN_RAD, cfg.shading_levels
            )

        shading = self._shading.get((id(rig), spec.mount_height, weather, tod), (rig,), make_shading)
        img = ground.render_background(tex, rays, shading, frame.ego)

        plan = self._plan(frame, rig, spec)
        for v in range(rig.num_views):
            objects.paint(img[v * h : (v + 1) * h], plan, v, cfg.antialias, cfg.subpixel_bits)

        if lighting.precipitation != "none":
            overlay = self._precip.get(
                (lighting.precipitation, h, w), (), lambda: precipitation.Overlay(lighting.precipitation, h, w, cfg)
            )
            img = precipitation.blend(
                img, overlay.alpha(frame, rig.num_views), precipitation.precipitation_rgb(lighting)
            )
        return img.reshape(rig.num_views, h, w, 3)

    def render_lidar(self, frame: SceneFrame) -> np.ndarray:
        """(beams, azimuth) float32 ranges in metres; ``no_return`` (0.0) where nothing is hit."""
        _, spec, _ = self._specs(frame)
        rays = self._lidar_rays.get(id(spec), (spec,), lambda: lidar.lidar_rays(spec))
        return lidar.cast(self._object_poses(frame, spec), spec, rays, self.config.lidar_cull_margin_cols)

    def render_bev(self, frame: SceneFrame) -> np.ndarray:
        """(h, w, c) uint8 {0, 1} map raster around the ego, forward up, ego's left on the left."""
        _, _, bev = self._specs(frame)
        return ground.render_bev(frame.map, bev, frame.ego, self.config.lane_line_width_m, self.config.subpixel_bits)

    # -- geometry helpers -------------------------------------------------------------------

    def _camera(self, frame: SceneFrame | None, view: int) -> CameraSpec:
        if frame is None:
            if self.rig is None:
                raise ValueError("project(None, ...) needs a simulator built with a rig")
            rig = self.rig
        else:
            rig, _, _ = self._specs(frame)
        if not 0 <= view < rig.num_views:
            raise IndexError(f"view {view} out of range for a rig of {rig.num_views} cameras")
        return rig.cameras[view]

    def project(self, frame: SceneFrame | None, view: int, points_lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole projection of LiDAR-frame points (N, 3) into camera ``view``.

        Returns uv (N, 2) float64 in pixels (pixel (col, row) spans [col, col + 1) x [row, row + 1),
        so its centre is at +0.5) and depth (N,) along the optical axis; depth <= 0 means behind the
        camera, and those points get uv = NaN.
        """
        cam = self._camera(frame, view)
        p = np.asarray(points_lidar, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points_lidar must have shape (N, 3), got {p.shape}")
        pc = (p - cam.t) @ cam.R
        depth = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (pc @ cam.K.T)[:, :2] / depth[:, None]
        uv[depth <= 0] = np.nan
        return uv, depth

    def object_boxes_2d(self, frame: SceneFrame, view: int) -> dict[str, tuple[int, int, int, int]]:
        """Pixel extents ``(x0, y0, x1, y1)`` (end-exclusive: ``img[y0:y1, x0:x1]``) of each object's
        projected 3D box, clipped to the image, for the objects in the view's frustum.

        Boxes crossing the near plane are clipped there first. Occlusion is not considered (see
        :meth:`object_crops`).
        """
        cam = self._camera(frame, view)
        _, spec, _ = self._specs(frame)
        corners = self._object_poses(frame, spec).corners
        out = {}
        for obj, cs in zip(frame.objects, corners, strict=True):
            box = cam.box_extent(cs, self.config.near_plane_m)
            if box is not None:
                out[obj.track_id] = box
        return out

    def object_masks(self, frame: SceneFrame) -> tuple[np.ndarray, np.ndarray]:
        """Where ``frame``'s objects are seen: camera pixels (V, H, W) bool of the visible objects
        (after occlusion, as :meth:`visible_pixels`) and LiDAR rays (beams, azimuth) bool whose
        return is an object's (the range map differs from the road-only one)."""
        rig, spec, _ = self._specs(frame)
        plan = self._plan(frame, rig, spec)
        ids = np.zeros((rig.num_views, *rig.resolution), dtype=np.int32)
        for v in range(rig.num_views):
            objects.paint(ids[v], plan, v, False, self.config.subpixel_bits, value=lambda o: o + 1)
        rays = self._lidar_rays.get(id(spec), (spec,), lambda: lidar.lidar_rays(spec))
        ground = lidar.cast(object_poses(replace(frame, objects=()), spec.mount_height), spec, rays, 0)
        return ids > 0, self.render_lidar(frame) != ground

    def visible_pixels(self, frame: SceneFrame) -> tuple[np.ndarray, np.ndarray]:
        """Per view and object: (visible pixels after occlusion, pixels of the unoccluded silhouette),
        both (V, N) int64, from an object-id rendering without anti-aliasing."""
        rig, spec, _ = self._specs(frame)
        h, w = rig.resolution
        n = len(frame.objects)
        plan = self._plan(frame, rig, spec)
        shift = self.config.subpixel_bits
        visible = np.zeros((rig.num_views, n), dtype=np.int64)
        silhouette = np.zeros((rig.num_views, n), dtype=np.int64)
        for v in range(rig.num_views):
            ids = np.zeros((h, w), dtype=np.int32)
            objects.paint(ids, plan, v, False, shift, value=lambda o: o + 1)
            visible[v] = np.bincount(ids.ravel(), minlength=n + 1)[1:]
            mask = np.zeros((h, w), dtype=np.uint8)
            on_view = plan.objects[plan.view(v)]
            for obj in np.unique(on_view).tolist():
                mask[:] = 0
                for poly in plan.polygons[plan.view(v)][on_view == obj]:
                    cv2.fillConvexPoly(mask, poly, 1, cv2.LINE_8, shift)
                silhouette[v, obj] = int(mask.sum())
        return visible, silhouette

    def object_crops(self, frame: SceneFrame, cameras: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The "image description" crop (h, w, 3) uint8 of each object from the view where most of it
        is visible; objects that are out of view, too small or mostly occluded get none.

        ``cameras`` are this frame's rendered images (rendered here when None).
        """
        rig, _, _ = self._specs(frame)
        if cameras is None:
            cameras = self.render_cameras(frame)
        h, w = rig.resolution
        if cameras.dtype != np.uint8 or cameras.shape != (rig.num_views, h, w, 3):
            raise ValueError(f"cameras must be uint8 {(rig.num_views, h, w, 3)}, got {cameras.dtype} {cameras.shape}")
        cfg = self.config
        visible, silhouette = self.visible_pixels(frame)
        fraction = visible / np.maximum(silhouette, 1)
        ok = (visible >= cfg.crop_min_visible_px) & (fraction >= cfg.crop_min_visible_fraction)
        score = np.where(ok, visible, -1)
        crops = {}
        boxes = [None] * rig.num_views
        for i, obj in enumerate(frame.objects):
            view = int(np.argmax(score[:, i]))
            if score[view, i] < 0:
                continue
            if boxes[view] is None:
                boxes[view] = self.object_boxes_2d(frame, view)
            if obj.track_id not in boxes[view]:
                continue
            x0, y0, x1, y1 = boxes[view][obj.track_id]
            mx, my = round(cfg.crop_margin * (x1 - x0)), round(cfg.crop_margin * (y1 - y0))
            x0, y0, x1, y1 = max(0, x0 - mx), max(0, y0 - my), min(w, x1 + mx), min(h, y1 + my)
            crops[obj.track_id] = cameras[view, y0:y1, x0:x1].copy()
        return crops
