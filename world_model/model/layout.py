"""Pixel-aligned layout: where the scene's road, lane lines and objects fall in every view.

The paper feeds boxes and the BEV map to the DiT only as cross-attention tokens; a small model
would have to learn 3-D projection from them. The layout raster does that projection
geometrically, per view at the latent resolution, and the DiT reads it as extra input channels
beside the noisy latent (:class:`~world_model.model.config.LayoutConfig`).

Every view is a bundle of rays from its sensor in the LiDAR frame: a camera's through its pixel
centres, the LiDAR view's through the (elevation, azimuth) of its range-map cells resampled to the
view size (as :func:`world_model.model.vae.lidar_to_images` resamples the range map). Each ray's
first hit is found exactly: the slab test against every object's yawed box, and the road plane
``z = -mount_height``. A ground hit reads the BEV raster the model is conditioned on (so the
layout and the map tokens can never disagree; beyond the raster the ground has no road class).
``supersample`` rays per latent cell side are averaged, so a channel holds the fraction of the
cell covered. Channels (:data:`LAYOUT_CHANNELS`):

* ``road``, ``lane_line``, ``road_edge``: the BEV's drivable_area / lane_divider / road_edge where
  the ray's first hit is the ground;
* ``vehicle``, ``ped_cyclist``, ``other_object``: the category group of the first object hit;
* ``nearness``: ``1 - range / lidar.max_range`` of the first hit (ground or object), 0 for rays
  that hit nothing within range; on the LiDAR view it is the range map the scene implies.

Occlusion between objects and of the road by objects follows from taking the first hit. The
ego's own body is not drawn (the sensors see past it).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from world_model.scene import CATEGORIES, SceneFrame
from world_model.sensors import CameraRig, LidarSpec

LAYOUT_GROUND_CHANNELS = {"road": "drivable_area", "lane_line": "lane_divider", "road_edge": "road_edge"}
# Category groups of the object channels (the segmentation metric's object classes).
LAYOUT_OBJECT_GROUPS: dict[str, tuple[str, ...]] = {
    "vehicle": ("car", "truck", "bus", "van", "motorcycle", "tree_truck", "cement_mixer"),
    "ped_cyclist": ("pedestrian", "cyclist"),
    "other_object": ("cone", "barrier"),
}
LAYOUT_CHANNELS = (*LAYOUT_GROUND_CHANNELS, *LAYOUT_OBJECT_GROUPS, "nearness")

_GROUP_OF = {cat: g for g, cats in LAYOUT_OBJECT_GROUPS.items() for cat in cats}
assert set(_GROUP_OF) == set(CATEGORIES), "every scene category needs a layout group"
_CHANNEL = {name: i for i, name in enumerate(LAYOUT_CHANNELS)}
# A hit closer than this to the ray's origin is ignored: the sensor sits inside no object.
_NEAR_M = 0.05
# Steps of a nearness byte (:func:`lidar_nearness`): 0.39 m at the default 100 m range.
NEARNESS_LEVELS = 255
# Steps of the range map's nearness (uint16, :func:`~world_model.raster.maps.range_nearness_maps`),
# which the range head stands the LiDAR's returns on: 1.5 mm at 100 m. In a byte's 0.39 m steps a car
# closing at a steady speed would read as standing still, then jumping: a policy's closing speed
# from two frames would swing by 2 m/s at 5 Hz.
RANGE_LEVELS = 65535


@functools.lru_cache(maxsize=16)
def _camera_rays(rig_key: tuple, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Per camera, rays through a ``rows x cols`` grid of cell centres spanning the image.

    Returns each camera's origin (Vc, 3) and its rays' unit directions (Vc, rows*cols, 3), LiDAR frame."""
    origins, dirs = [], []
    for k, r, t, width, height in rig_key:
        k, r, t = (np.frombuffer(a, dtype=np.float64).reshape(s) for a, s in ((k, (3, 3)), (r, (3, 3)), (t, (3,))))
        u = (np.arange(cols) + 0.5) * width / cols
        v = (np.arange(rows) + 0.5) * height / rows
        uu, vv = np.meshgrid(u, v)
        cam = np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)], axis=-1)
        d = cam.reshape(-1, 3) @ r.T
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        origins.append(t)
    return np.stack(origins), np.stack(dirs)


@functools.lru_cache(maxsize=16)
def _lidar_rays(spec: LidarSpec, rows: int, cols: int) -> np.ndarray:
    """Unit directions (rows*cols, 3) of the LiDAR view's cells: the range map's elevations and
    azimuths sampled where a bilinear resize to ``rows x cols`` (half-pixel centres) reads them."""
    beam = np.clip((np.arange(rows) + 0.5) * spec.beams / rows - 0.5, 0.0, spec.beams - 1)
    col = (np.arange(cols) + 0.5) * spec.azimuth / cols - 0.5
    el_step = (spec.elevation_max_deg - spec.elevation_min_deg) / max(spec.beams - 1, 1)
    el = np.deg2rad(spec.elevation_max_deg - beam * el_step)[:, None]
    az = (np.pi - 2.0 * np.pi / spec.azimuth * col)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)
    return d.reshape(-1, 3)


def _rig_key(rig: CameraRig) -> tuple:
    return tuple((c.K.tobytes(), c.R.tobytes(), c.t.tobytes(), c.width, c.height) for c in rig.cameras)


def view_rays(rig: CameraRig, lidar: LidarSpec, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays of every view (cameras in rig order, then the LiDAR), in the LiDAR frame: each view's
    origin (V, 3) and its rays' unit directions (V, rows*cols, 3)."""
    cam_o, cam_d = _camera_rays(_rig_key(rig), rows, cols)
    lid_d = _lidar_rays(lidar, rows, cols)
    return np.concatenate([cam_o, np.zeros((1, 3))]), np.concatenate([cam_d, lid_d[None]])


def _first_hits(frame: SceneFrame, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each ray's distance to the road plane and to the first object it enters (inf where none),
    and that object's layout channel (-1 where none), all (V*n,) in view-major order.
    origins (V, 3): each view's sensor; dirs (V, n, 3): its rays' unit directions; LiDAR frame.

    An object covers a small part of the views: one product of every ray with every object's
    centre finds the rays that pass within its bounding sphere (kept with a hair of slack, so
    rounding never drops a ray the box could stop), and only those (ray, object) pairs are
    slab-tested against the yawed box, all at once. Of the boxes a ray enters, the nearest
    counts; at equal distance, the earlier object in the frame's order."""
    v, n, _ = dirs.shape
    d = dirs.reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, (-frame.lidar.mount_height - np.repeat(origins[:, 2], n)) / d[:, 2], np.inf)
    t_obj = np.full(len(d), np.inf)
    obj_group = np.full(len(d), -1)
    boxes = frame.object_boxes_lidar()
    if not boxes:
        return t_ground, t_obj, obj_group
    centers = np.array([b.center for b in boxes], np.float64)  # (K, 3)
    sizes = np.array([b.size for b in boxes], np.float64)
    yaws = np.array([b.yaw for b in boxes], np.float64)
    groups = np.array([_CHANNEL[_GROUP_OF.get(o.category, "other_object")] for o in frame.objects])
    radius2 = 0.25 * (sizes**2).sum(axis=1)  # (K,)
    rel = centers[None] - origins[:, None]  # (V, K, 3): each object's centre seen from each sensor
    dist2 = (rel**2).sum(axis=-1)[:, None]  # (V, 1, K)
    along = dirs @ rel.transpose(0, 2, 1)  # (V, n, K)
    slack = 1e-9 * (1.0 + dist2)
    near = (dist2 - along**2 <= radius2 + slack) & (along > -np.sqrt(radius2) - slack)
    view, ray, obj = np.nonzero(near)
    ray = view * n + ray

    # The slab test in each box's axes (rotation by -yaw about +z), written out per component so
    # a pair's result does not depend on how many pairs there are.
    c, s = np.cos(yaws)[obj], np.sin(yaws)[obj]
    r, dr = rel[view, obj], d[ray]
    o_box = np.stack([-(c * r[:, 0] + s * r[:, 1]), -(c * r[:, 1] - s * r[:, 0]), -r[:, 2]], axis=1)
    d_box = np.stack([c * dr[:, 0] + s * dr[:, 1], c * dr[:, 1] - s * dr[:, 0], dr[:, 2]], axis=1)
    half = 0.5 * sizes[obj]
    inv = 1.0 / np.where(np.abs(d_box) < 1e-12, 1e-12, d_box)
    t1, t2 = (-half - o_box) * inv, (half - o_box) * inv
    t_in = np.minimum(t1, t2).max(axis=1)
    hit = (np.maximum(t1, t2).min(axis=1) >= t_in) & (t_in > _NEAR_M)
    ray, obj, t_in = ray[hit], obj[hit], t_in[hit]
    order = np.lexsort((obj, t_in, ray))  # per ray, nearest first, then the frame's order
    ray, obj, t_in = ray[order], obj[order], t_in[order]
    first = np.ones(len(ray), bool)
    first[1:] = ray[1:] != ray[:-1]
    t_obj[ray[first]] = t_in[first]
    obj_group[ray[first]] = groups[obj[first]]
    return t_ground, t_obj, obj_group


def _nearness(first: np.ndarray, max_range: float) -> np.ndarray:
    """``1 - range / max_range`` of first hits, 0 for those out of range."""
    return np.where(first < max_range, 1.0 - first / max_range, 0.0).astype(np.float32)


def lidar_nearness(frame: SceneFrame, lidar: LidarSpec, hw: tuple[int, int]) -> np.ndarray:
    """(H, W) uint8: the range map the scene implies on the LiDAR view at ``hw``, one ray per cell
    (the ``nearness`` channel of :func:`layout_raster` without averaging), in
    :data:`NEARNESS_LEVELS` steps of ``1 - range / max_range``, 0 where nothing is in range."""
    d = _lidar_rays(lidar, *hw)
    t_ground, t_obj, _ = _first_hits(frame, np.zeros((1, 3)), d[None])
    near = _nearness(np.minimum(t_ground, t_obj), lidar.max_range)
    return np.rint(near * NEARNESS_LEVELS).astype(np.uint8).reshape(hw)


def layout_raster(
    frame: SceneFrame,
    bev: np.ndarray,
    lidar: LidarSpec,
    latent_hw: tuple[int, int],
    supersample: int,
) -> np.ndarray:
    """The layout of one frame: (V, len(LAYOUT_CHANNELS), h, w) float32 in [0, 1].

    Args:
        frame: the scene at this tick (its rig gives the cameras, its LiDAR the mount height).
        bev: (bh, bw, c) the frame's BEV raster, classes in ``frame.bev.classes`` order.
        lidar: the LiDAR whose range map forms the last view (geometry and ``max_range``).
        latent_hw: (h, w) of the output grid, the latent resolution.
        supersample: rays per output cell side.
    """
    if supersample < 1:
        raise ValueError(f"layout supersample must be >= 1, got {supersample}")
    missing = [c for c in LAYOUT_GROUND_CHANNELS.values() if c not in frame.bev.classes]
    if missing:
        raise ValueError(f"the layout reads BEV classes {missing}, missing from the frame's BEV {frame.bev.classes}")
    bev = np.asarray(bev)
    if bev.shape != frame.bev.shape:
        raise ValueError(f"bev must have the frame's BEV shape {frame.bev.shape}, got {bev.shape}")
    h, w = latent_hw
    rows, cols = h * supersample, w * supersample
    origins, dirs = view_rays(frame.rig, lidar, rows, cols)
    v, n = dirs.shape[:2]
    d = dirs.reshape(-1, 3)
    t_ground, t_obj, obj_group = _first_hits(frame, origins, dirs)
    first = np.minimum(t_ground, t_obj)
    in_range = first < lidar.max_range
    out = np.zeros((len(LAYOUT_CHANNELS), len(d)), np.float32)
    out[_CHANNEL["nearness"]] = _nearness(first, lidar.max_range)
    on_obj = in_range & (t_obj <= t_ground)
    out[obj_group[on_obj], np.flatnonzero(on_obj)] = 1.0

    ground = np.flatnonzero(in_range & ~on_obj & np.isfinite(t_ground))
    p = origins[ground // n] + t_ground[ground, None] * d[ground]
    spec = frame.bev
    bh, bw, _ = spec.shape
    r = np.floor((spec.forward_m - p[:, 0]) / spec.m_per_px).astype(np.int64)
    c = np.floor((spec.half_width_m - p[:, 1]) / spec.m_per_px).astype(np.int64)
    inside = (r >= 0) & (r < bh) & (c >= 0) & (c < bw)
    ground, r, c = ground[inside], r[inside], c[inside]
    for name, bev_class in LAYOUT_GROUND_CHANNELS.items():
        out[_CHANNEL[name], ground] = bev[r, c, spec.classes.index(bev_class)]

    cells = out.reshape(len(LAYOUT_CHANNELS), v, h, supersample, w, supersample).mean(axis=(3, 5))
    return np.ascontiguousarray(cells.transpose(1, 0, 2, 3))


def layout_sequence(
    frames: Sequence[SceneFrame], bev: np.ndarray, lidar: LidarSpec, latent_hw: tuple[int, int], supersample: int
) -> np.ndarray:
    """(T, V, len(LAYOUT_CHANNELS), h, w) float32: :func:`layout_raster` of every frame."""
    return np.stack([layout_raster(f, b, lidar, latent_hw, supersample) for f, b in zip(frames, bev, strict=True)])
