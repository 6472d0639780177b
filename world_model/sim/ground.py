"""The road in the cameras (sky + ground per pixel) and in the BEV raster.

Camera pixels below the horizon see the road plane (z = -mount_height in the LiDAR frame). Their
hit points are fixed in the ego frame, so they are computed once per rig, together with the
per-pixel light and fog of each lighting; each frame only moves them to world coordinates and
looks the labels up in the map's texture (:mod:`world_model.sim.texture`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from world_model.scene import EgoState, MapGeometry
from world_model.sensors import BevSpec, CameraRig
from world_model.sim.lighting import Lighting
from world_model.sim.texture import MapTexture


@dataclass(frozen=True)
class GroundRays:
    """Per-rig ray geometry, all views stacked vertically: image arrays are (V*H, W); G ground pixels."""

    distance: np.ndarray  # (V*H, W) float64 metres along the ray to the road, inf for sky
    elevation: np.ndarray  # (V*H, W) float64 elevation angle of the ray, radians
    ground_index: np.ndarray  # (G,) flat indices of the pixels that see the road
    ground_xy: np.ndarray  # (G, 1, 2) float32 ego-frame x, y of their hit points (cv2 point layout)


def ground_rays(rig: CameraRig, mount_height: float, max_distance: float) -> GroundRays:
    """Where every camera pixel's ray meets the road plane (pixel centres at +0.5).

    Hits farther than ``max_distance`` are pulled back to it along the ray (the horizon band).
    """
    h, w = rig.resolution
    xs, ys, ds, els = [], [], [], []
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    for cam in rig.cameras:
        rays = pix @ np.linalg.inv(cam.K).T @ cam.R.T  # (H, W, 3) LiDAR frame directions
        norm = np.linalg.norm(rays, axis=-1)
        els.append(np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1])))
        down = rays[..., 2] < 0
        s = np.where(down, (-mount_height - cam.t[2]) / np.where(down, rays[..., 2], -1.0), np.inf)
        ground = down & (s > 0)
        s = np.minimum(s, max_distance / np.maximum(norm, 1e-12))
        xs.append(cam.t[0] + s * rays[..., 0])
        ys.append(cam.t[1] + s * rays[..., 1])
        ds.append(np.where(ground, s * norm, np.inf))
    distance = np.concatenate(ds)
    index = np.flatnonzero(np.isfinite(distance))
    xy = np.stack([np.concatenate(xs).reshape(-1)[index], np.concatenate(ys).reshape(-1)[index]], -1)
    return GroundRays(
        distance=distance,
        elevation=np.concatenate(els),
        ground_index=index,
        ground_xy=xy.astype(np.float32).reshape(-1, 1, 2),
    )


@dataclass(frozen=True)
class BackgroundShading:
    """Per (rig, lighting): every background pixel is one lookup into a palette of final colours.

    A ground pixel's colour is ``albedo(label) * light * (1 - fog) * tint + fog * fog_color``; its
    (light * (1 - fog), fog) pair is fixed per pixel, so it is quantized and every distinct pair gets
    256 palette rows (one per label). Sky pixels get one row each. Colours are packed RGBA uint32 so
    that lookups move one machine word per pixel.
    """

    base: np.ndarray  # (V*H*W,) int32 palette row of each pixel (ground: + its label)
    palette: np.ndarray  # (rows,) uint32 packed RGBA


def _pack_rgba(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) float colours -> (...,) uint32 whose bytes are R, G, B, 255 in memory order."""
    rgba = np.concatenate([np.clip(np.round(rgb), 0, 255), np.full(rgb.shape[:-1] + (1,), 255.0)], -1)
    return np.ascontiguousarray(rgba.astype(np.uint8)).view(np.uint32)[..., 0]


def background_shading(
    rays: GroundRays,
    lighting: Lighting,
    albedo: np.ndarray,
    sky_distance: float,
    sky_span: float,
    levels: int,
) -> BackgroundShading:
    """``albedo``: (256, 3) per label; ``levels``: quantization steps per unit of light and of fog."""
    dist = rays.distance.reshape(-1)[rays.ground_index]
    fog = lighting.fog_factor(dist)
    gx, gy = rays.ground_xy[:, 0, 0].astype(np.float64), rays.ground_xy[:, 0, 1].astype(np.float64)
    light = lighting.ambient + lighting.sun * max(lighting.sun_direction[2], 0.0) + lighting.headlight(gx, gy)
    key = np.stack([np.round(light * (1.0 - fog) * levels), np.round(fog * levels)], -1).astype(np.int64)
    combos, inverse = np.unique(key, axis=0, return_inverse=True)
    gain, fogq = combos[:, 0] / levels, combos[:, 1] / levels
    table = (
        albedo[None].astype(np.float64) * (gain[:, None, None] * lighting.tint)
        + fogq[:, None, None] * lighting.fog_color
    ).reshape(-1, 3)  # (S * 256, 3)
    t = np.clip(rays.elevation / sky_span, 0.0, 1.0).reshape(-1, 1)
    sky_fog = float(lighting.fog_factor(sky_distance))
    sky = (1 - sky_fog) * ((1 - t) * lighting.sky_horizon + t * lighting.sky_zenith) + sky_fog * lighting.fog_color
    base = len(table) + np.arange(len(sky), dtype=np.int32)  # every pixel its own sky row ...
    base[rays.ground_index] = (inverse.reshape(-1) * 256).astype(np.int32)  # ... unless it sees the road
    return BackgroundShading(base=base, palette=_pack_rgba(np.concatenate([table, sky])))


def render_background(tex: MapTexture, rays: GroundRays, shading: BackgroundShading, ego: EgoState) -> np.ndarray:
    """Sky and road for all views, (V*H, W, 3) uint8."""
    h, w = rays.distance.shape
    rows = shading.base.copy()
    rows[rays.ground_index] += tex.lookup_ego(rays.ground_xy, ego.x, ego.y, ego.yaw)
    rgba = np.take(shading.palette, rows).view(np.uint8).reshape(h, w, 4)
    return cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB)


# -- BEV ---------------------------------------------------------------------------------------


def render_bev(m: MapGeometry, bev: BevSpec, ego: EgoState, line_width_m: float, shift: int) -> np.ndarray:
    """The map around the ego as a {0,1} uint8 raster (h, w, c), classes in ``bev.classes`` order.

    Lane dividers are the painted lane lines (kind "none" is an unpainted boundary and is left out).
    """
    h, w, _ = bev.shape
    scale = (1 << shift) / bev.m_per_px
    half = 0.5 * (1 << shift)
    ego_xy = np.array([ego.x, ego.y])
    c, s = math.cos(ego.yaw), math.sin(ego.yaw)
    reach = math.hypot(max(bev.forward_m, bev.backward_m), bev.half_width_m)

    def to_px(p: np.ndarray) -> np.ndarray | None:
        p = np.asarray(p, dtype=np.float64)
        if len(p) == 0 or _far(p, ego_xy, reach):
            return None
        d = p - ego_xy
        ex = c * d[:, 0] + s * d[:, 1]
        ey = -s * d[:, 0] + c * d[:, 1]
        cols = (bev.half_width_m - ey) * scale - half
        rows = (bev.forward_m - ex) * scale - half
        return np.round(np.stack([cols, rows], axis=1)).astype(np.int32)

    thickness = max(1, round(line_width_m / bev.m_per_px))
    planes = {}
    for name in bev.classes:
        plane = np.zeros((h, w), dtype=np.uint8)
        if name == "drivable_area":
            for poly in m.drivable_area:
                px = to_px(poly)
                if px is not None:
                    cv2.fillPoly(plane, [px], 1, cv2.LINE_8, shift)
        elif name in ("lane_divider", "road_edge"):
            lines = (
                [ln.points for ln in m.lane_lines if ln.kind != "none"]
                if name == "lane_divider"
                else list(m.road_edges)
            )
            pxs = [px for px in (to_px(p) for p in lines if len(p) >= 2) if px is not None]
            if pxs:
                cv2.polylines(plane, pxs, False, 1, thickness, cv2.LINE_8, shift)
        else:
            raise ValueError(
                f"unsupported BEV class {name!r}; the simulator draws drivable_area, lane_divider, road_edge"
            )
        planes[name] = plane
    return np.stack([planes[n] for n in bev.classes], axis=-1)


def _far(points: np.ndarray, centre: np.ndarray, reach: float) -> bool:
    """True when no segment of the polyline/polygon comes within ``reach`` of ``centre`` (bbox test)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    nearest = np.clip(centre, lo, hi)
    return bool(np.hypot(*(nearest - centre)) > reach)
