"""The road: a world-aligned label texture per map, per-rig ground rays, and the BEV raster.

Camera pixels below the horizon see the road plane (z = -mount_height in the LiDAR frame). Their
hit points are fixed in the ego frame, so they are computed once per rig; each frame only moves
them to world coordinates and looks up a label texture rasterized once per map. Labels index a
palette that depends on the weather (asphalt, verge, paint), with a few low-frequency variations
of each surface so that motion over the road is visible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from world_model.scene import EgoState, MapGeometry
from world_model.sensors import BevSpec, CameraRig
from world_model.sim.config import SimConfig
from world_model.sim.lighting import Lighting

# Palette brightness spread of the surface variations (fraction of the albedo).
SURFACE_VARIATION = 0.12


def labels_layout(levels: int) -> tuple[int, int, int, int]:
    """(first off-road label, first road label, marking label, road-edge label)."""
    return 0, levels, 2 * levels, 2 * levels + 1


def dash_segments(points: np.ndarray, dash: float, gap: float) -> list[np.ndarray]:
    """Split a polyline (N, 2) into dashes of length ``dash`` separated by ``gap`` (arc length)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    total = arc[-1]
    if gap <= 0 or total <= 0:
        return [points]
    out = []
    for s0 in np.arange(0.0, total, dash + gap):
        s1 = min(s0 + dash, total)
        inner = arc[(arc > s0) & (arc < s1)]
        s = np.concatenate([[s0], inner, [s1]])
        out.append(np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], axis=1))
    return out


def _map_points(m: MapGeometry) -> np.ndarray:
    parts = [p for p in m.drivable_area] + list(m.road_edges) + [ln.points for ln in m.lane_lines]
    parts = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in parts]
    return np.concatenate(parts) if parts else np.zeros((0, 2))


@dataclass(frozen=True)
class MapTexture:
    """Label texture: texel (row, col) covers world x in x0 + res*[col, col+1), y in y0 + res*[row, row+1)."""

    labels: np.ndarray  # (Ht, Wt) uint8
    x0: float
    y0: float
    m_per_px: float

    def lookup(self, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
        """Labels at world points (any shape); points off the texture read its off-road border."""
        ht, wt = self.labels.shape
        col = ((wx - self.x0) * (1.0 / self.m_per_px)).astype(np.int32)
        row = ((wy - self.y0) * (1.0 / self.m_per_px)).astype(np.int32)
        np.clip(col, 0, wt - 1, out=col)
        np.clip(row, 0, ht - 1, out=row)
        row *= wt
        row += col
        return np.take(self.labels.reshape(-1), row)


def rasterize_map(m: MapGeometry, config: SimConfig) -> MapTexture:
    """Rasterize drivable area, painted lines and road edges into a label texture (once per map)."""
    pts = _map_points(m)
    if len(pts) == 0:
        pts = np.zeros((1, 2))
    lo = pts.min(axis=0) - config.texture_margin_m
    hi = pts.max(axis=0) + config.texture_margin_m
    extent = hi - lo
    res = max(config.texture_m_per_px, math.sqrt(extent[0] * extent[1] / config.texture_max_texels))
    wt, ht = (int(math.ceil(e / res)) for e in extent)
    levels = config.texture_noise_levels
    off0, road0, marking, edge = labels_layout(levels)

    rng = np.random.default_rng(config.texture_seed)
    cells = (
        max(2, int(ht * res / config.texture_noise_cell_m) + 2),
        max(2, int(wt * res / config.texture_noise_cell_m) + 2),
    )
    noise = cv2.resize(rng.random(cells, dtype=np.float32), (wt, ht), interpolation=cv2.INTER_LINEAR)
    variation = np.minimum((noise * levels).astype(np.uint8), levels - 1)

    shift = config.subpixel_bits
    scale = (1 << shift) / res

    def to_px(p: np.ndarray) -> np.ndarray:
        return np.round((np.asarray(p, dtype=np.float64) - lo) * scale - 0.5 * (1 << shift)).astype(np.int32)

    road = np.zeros((ht, wt), dtype=np.uint8)
    for poly in m.drivable_area:
        cv2.fillPoly(road, [to_px(poly)], 1, cv2.LINE_8, shift)
    labels = variation + np.where(road > 0, road0, off0).astype(np.uint8)

    paint = np.zeros((ht, wt), dtype=np.uint8)
    line_px = max(1, round(config.lane_line_width_m / res))
    for ln in m.lane_lines:
        if ln.kind == "none" or len(ln.points) < 2:
            continue
        segs = (
            [ln.points]
            if ln.kind == "solid"
            else dash_segments(ln.points, config.dash_length_m, config.dash_gap_m)
        )
        cv2.polylines(paint, [to_px(s) for s in segs], False, 1, line_px, cv2.LINE_8, shift)
    labels[paint > 0] = marking
    paint[:] = 0
    edge_px = max(1, round(config.road_edge_width_m / res))
    edges = [to_px(e) for e in m.road_edges if len(e) >= 2]
    if edges:
        cv2.polylines(paint, edges, False, 1, edge_px, cv2.LINE_8, shift)
    labels[paint > 0] = edge
    return MapTexture(labels=labels, x0=float(lo[0]), y0=float(lo[1]), m_per_px=float(res))


def palette(lighting: Lighting, levels: int) -> np.ndarray:
    """(256, 3) float32 albedo of every label under ``lighting``."""
    off0, road0, marking, edge = labels_layout(levels)
    pal = np.zeros((256, 3), dtype=np.float32)
    ramp = 1.0 + SURFACE_VARIATION * (np.arange(levels) / max(levels - 1, 1) - 0.5) * 2
    pal[off0 : off0 + levels] = ramp[:, None] * lighting.offroad
    pal[road0 : road0 + levels] = ramp[:, None] * lighting.road
    pal[marking] = lighting.marking
    pal[edge] = lighting.marking
    return pal


@dataclass(frozen=True)
class GroundRays:
    """Per-rig ray geometry, all views stacked vertically: arrays are (V*H, W)."""

    gx: np.ndarray  # float32 ego-frame x of the ground hit (0 for sky pixels)
    gy: np.ndarray  # float32
    distance: np.ndarray  # float64 metres along the ray to the hit, inf for sky
    elevation: np.ndarray  # float64 elevation angle of the ray, radians

    @property
    def sky(self) -> np.ndarray:
        return ~np.isfinite(self.distance)


def ground_rays(rig: CameraRig, mount_height: float, max_distance: float) -> GroundRays:
    """Where every camera pixel's ray meets the road plane (pixel centres at +0.5)."""
    h, w = rig.resolution
    gxs, gys, ds, els = [], [], [], []
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    for cam in rig.cameras:
        rays = pix @ np.linalg.inv(cam.K).T @ cam.R.T  # (H, W, 3) LiDAR frame directions
        norm = np.linalg.norm(rays, axis=-1)
        horiz = np.hypot(rays[..., 0], rays[..., 1])
        els.append(np.arctan2(rays[..., 2], horiz))
        down = rays[..., 2] < 0
        with np.errstate(divide="ignore"):
            s = np.where(down, (-mount_height - cam.t[2]) / np.where(down, rays[..., 2], -1.0), np.inf)
        dist = s * norm
        ground = down & (s > 0)
        s_cap = np.minimum(s, max_distance / np.maximum(norm, 1e-12))
        gxs.append(np.where(ground, cam.t[0] + s_cap * rays[..., 0], 0.0))
        gys.append(np.where(ground, cam.t[1] + s_cap * rays[..., 1], 0.0))
        ds.append(np.where(ground, np.minimum(dist, max_distance), np.inf))
    return GroundRays(
        gx=np.concatenate(gxs).astype(np.float32),
        gy=np.concatenate(gys).astype(np.float32),
        distance=np.concatenate(ds),
        elevation=np.concatenate(els),
    )


@dataclass(frozen=True)
class BackgroundShading:
    """Per (rig, lighting): pixel = albedo * gain + add. (V*H, W, 3) float32 each; sky has gain 0."""

    gain: np.ndarray
    add: np.ndarray


def background_shading(
    rays: GroundRays, lighting: Lighting, sky_distance: float, sky_span: float
) -> BackgroundShading:
    sky = rays.sky
    dist = np.where(sky, 0.0, rays.distance)
    fog = lighting.fog_factor(dist)
    light = lighting.ambient + lighting.sun * max(lighting.sun_direction[2], 0.0)
    light = light + lighting.headlight(rays.gx.astype(np.float64), rays.gy.astype(np.float64))
    gain = (light * (1.0 - fog))[..., None] * lighting.tint
    add = fog[..., None] * lighting.fog_color
    t = np.clip(rays.elevation / sky_span, 0.0, 1.0)[..., None]
    sky_rgb = (1 - t) * lighting.sky_horizon + t * lighting.sky_zenith
    sky_fog = float(lighting.fog_factor(sky_distance))
    sky_rgb = (1 - sky_fog) * sky_rgb + sky_fog * lighting.fog_color
    gain[sky] = 0.0
    add[sky] = sky_rgb[sky]
    return BackgroundShading(gain=gain.astype(np.float32), add=add.astype(np.float32))


def render_background(
    tex: MapTexture, rays: GroundRays, shading: BackgroundShading, pal: np.ndarray, ego: EgoState
) -> np.ndarray:
    """Sky and road for all views, (V*H, W, 3) uint8."""
    c, s = np.float32(math.cos(ego.yaw)), np.float32(math.sin(ego.yaw))
    wx = rays.gx * c - rays.gy * s
    wx += np.float32(ego.x)
    wy = rays.gx * s + rays.gy * c
    wy += np.float32(ego.y)
    rgb = np.take(pal, tex.lookup(wx, wy), axis=0)
    rgb *= shading.gain
    rgb += shading.add
    np.clip(rgb, 0.0, 255.0, out=rgb)
    return rgb.astype(np.uint8)


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
