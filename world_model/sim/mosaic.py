"""A single overview image of an observation: camera ring, LiDAR range image, BEV with boxes."""

from __future__ import annotations

import math

import cv2
import numpy as np

from world_model.observation import Observation
from world_model.scene import SceneFrame
from world_model.sensors import DEFAULT_CAMERA_NAMES, CameraRig, default_rig

BACKGROUND = (16, 16, 16)
BEV_CLASS_COLORS = {
    "drivable_area": (70, 70, 78),
    "lane_divider": (235, 235, 235),
    "road_edge": (230, 60, 50),
}
EGO_COLOR = (60, 220, 90)
LIDAR_MAX_M = 100.0  # colour-map scale of the range image
LIDAR_ROWS_PER_BEAM = 2  # vertical stretch of the range image before fitting the mosaic width


def ring_layout(rig: CameraRig | None, views: int) -> list[list[int]]:
    """Rows of view indices: forward-facing cameras on top (left to right as seen by the driver),
    rear-facing below (BACK_LEFT, BACK, BACK_RIGHT for the default rig). One row without a rig."""
    if rig is None or rig.num_views != views:
        return [list(range(views))]
    yaws = [math.degrees(c.yaw) for c in rig.cameras]
    front = sorted((i for i, y in enumerate(yaws) if abs(y) <= 90), key=lambda i: -yaws[i])
    back = sorted((i for i, y in enumerate(yaws) if abs(y) > 90), key=lambda i: yaws[i] % 360)
    return [r for r in (front, back) if r]


def _camera_grid(cams: np.ndarray, rows: list[list[int]]) -> np.ndarray:
    _, h, w, _ = cams.shape
    cols = max(len(r) for r in rows)
    grid = np.full((h * len(rows), w * cols, 3), BACKGROUND, dtype=np.uint8)
    for r, row in enumerate(rows):
        pad = (cols - len(row)) * w // 2
        for c, v in enumerate(row):
            grid[r * h : (r + 1) * h, pad + c * w : pad + (c + 1) * w] = cams[v]
    return grid


def lidar_image(ranges: np.ndarray, width: int) -> np.ndarray:
    """Colour-mapped range image (near = warm, log scale), no-return black, resized to ``width``."""
    norm = np.clip(np.log1p(np.maximum(ranges, 0.0)) / np.log1p(LIDAR_MAX_M), 0.0, 1.0)
    img = cv2.applyColorMap(((1.0 - norm) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    img = np.where((ranges > 0)[..., None], img, 0).astype(np.uint8)
    height = max(1, ranges.shape[0] * LIDAR_ROWS_PER_BEAM * width // max(ranges.shape[1], 1))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_NEAREST)


def bev_image(bev: np.ndarray, size: int, frame: SceneFrame | None) -> np.ndarray:
    """BEV classes painted in order, upscaled to ``size``, with object footprints and the ego."""
    h, w, _ = bev.shape
    classes = frame.bev.classes if frame is not None else tuple(BEV_CLASS_COLORS)[: bev.shape[-1]]
    img = np.full((h, w, 3), BACKGROUND, dtype=np.uint8)
    for c, name in enumerate(classes):
        img[bev[..., c] > 0] = BEV_CLASS_COLORS.get(name, (200, 200, 0))
    scale = size / max(h, w)
    out = cv2.resize(img, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_NEAREST)
    if frame is None:
        return out
    spec = frame.bev
    px_per_m = scale / spec.m_per_px

    def to_px(xy: np.ndarray) -> np.ndarray:
        cols = (spec.half_width_m - xy[:, 1]) * px_per_m
        rows = (spec.forward_m - xy[:, 0]) * px_per_m
        return np.round(np.stack([cols, rows], 1) * 16).astype(np.int32)

    for obj, corners in zip(frame.objects, frame.object_corners_lidar(), strict=True):
        cv2.fillConvexPoly(out, to_px(corners[[0, 1, 5, 4], :2]), tuple(int(c) for c in obj.color), cv2.LINE_AA, 4)
    e = frame.ego
    l, wd = e.size[0] / 2, e.size[1] / 2
    ego = np.array([[l, wd], [l, -wd], [-l, -wd], [-l, wd]])
    cv2.fillConvexPoly(out, to_px(ego), EGO_COLOR, cv2.LINE_AA, 4)
    return out


def mosaic(obs: Observation, frame: SceneFrame | None = None, rig: CameraRig | None = None) -> np.ndarray:
    """All camera views in ring layout, the BEV (when present) to their right and the colour-mapped
    LiDAR range image below, as one uint8 (H, W, 3) RGB image."""
    cameras, lidar = obs.sensor("cameras"), obs.sensor("lidar")  # both, or SensorNotDecoded
    rig = rig if rig is not None else (frame.rig if frame is not None else None)
    if rig is None and cameras.shape[0] == len(DEFAULT_CAMERA_NAMES):
        rig = default_rig(width=cameras.shape[2], height=cameras.shape[1])
    top = _camera_grid(cameras, ring_layout(rig, cameras.shape[0]))
    if obs.bev is not None:
        panel = bev_image(obs.bev, top.shape[0], frame)
        pad = np.full((top.shape[0], panel.shape[1], 3), BACKGROUND, dtype=np.uint8)
        pad[: panel.shape[0]] = panel[: top.shape[0]]
        top = np.concatenate([top, pad], axis=1)
    return np.concatenate([top, lidar_image(lidar, top.shape[1])], axis=0)
