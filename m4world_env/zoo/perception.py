"""What the zoo's modular policies perceive: pure functions of one LiDAR range map or one camera
image and the sensors' geometry.

* LiDAR points and ground removal: a return is an obstacle when it stands higher above the flat
  road than :data:`OBSTACLE_MIN_HEIGHT_M` (the road is the plane ``mount_height`` below the LiDAR).
* :func:`forward_gap`: the distance ahead to the nearest obstacle return inside a corridor of the
  ego's width, from the beams of an elevation band.
* :func:`lane_markings`: the lateral positions of the painted lines nearest the ego on either side,
  found as bright, narrow peaks in the bottom rows of a forward camera and projected onto the road
  plane through the camera's intrinsics and pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from world_model.sensors import PIXEL_CENTRE, CameraSpec, LidarSpec, road_points

# Higher than the range noise of a ground return (a 10% range error at 20 m on a -5 deg beam lifts
# it by ~0.2 m) and lower than any vehicle's bumper.
OBSTACLE_MIN_HEIGHT_M = 0.5
# highway-env's lane width: where only one side's marking is seen, the centre is half of it away.
LANE_WIDTH_M = 4.0
# A marking nearer than this to the camera's axis is the ego driving on it, not a lane's side; one
# farther than a lane width is the next lane's (seen where the nearest line is dashed).
MIN_MARKING_OFFSET_M = 0.3
MAX_MARKING_OFFSET_M = 0.9 * LANE_WIDTH_M
# A row's marking farther than this from the band's median on its side is another line.
MARKING_OUTLIER_M = 0.5


def lidar_points(
    ranges: np.ndarray, spec: LidarSpec, beams: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x forward, y left, height above the road) of every cell of a ``(beams, azimuth)`` range map,
    each ``(beams, azimuth)``; cells without a return hold NaN. With ``beams`` ((beams,) bool),
    only those rows: ``ranges`` is then the map's selected rows."""
    rays = spec.ray_directions() if beams is None else spec.ray_directions()[beams]
    r = np.where(ranges > spec.no_return, ranges, np.nan)
    return r * rays[..., 0], r * rays[..., 1], spec.mount_height + r * rays[..., 2]


def beam_band(spec: LidarSpec, low_deg: float, high_deg: float) -> np.ndarray:
    """(beams,) bool: the beams whose elevation lies in ``[low_deg, high_deg]``."""
    el = np.rad2deg(spec.elevations())
    return (el >= low_deg - 1e-9) & (el <= high_deg + 1e-9)


def forward_gap(
    ranges: np.ndarray,
    spec: LidarSpec,
    *,
    half_width_m: float,
    beams: np.ndarray,
    min_height_m: float = OBSTACLE_MIN_HEIGHT_M,
) -> float:
    """Distance ahead (m, along x from the LiDAR) of the nearest obstacle return with ``|y| <
    half_width_m`` on the selected ``beams`` ((beams,) bool); ``inf`` when there is none."""
    x, y, height = lidar_points(ranges[beams], spec, beams)
    hit = (x > 0) & (np.abs(y) < half_width_m) & (height > min_height_m)
    return float(x[hit].min()) if hit.any() else float("inf")


@dataclass(frozen=True)
class Markings:
    """Lateral positions (m, + left, at the band's mean distance ahead) of the nearest marking on
    each side, NaN when not seen, and the lane's heading relative to the ego (rad, + turns left;
    0 when it could not be measured)."""

    left_m: float
    right_m: float
    heading: float

    @property
    def centre_m(self) -> float:
        """The lane centre's lateral offset (+ left): the midpoint of both markings, or half a lane
        from the one seen; NaN when neither is."""
        if np.isfinite(self.left_m) and np.isfinite(self.right_m):
            return 0.5 * (self.left_m + self.right_m)
        if np.isfinite(self.left_m):
            return self.left_m - 0.5 * LANE_WIDTH_M
        if np.isfinite(self.right_m):
            return self.right_m + 0.5 * LANE_WIDTH_M
        return float("nan")


def marking_peaks(luminance: np.ndarray, min_contrast: float, max_width_px: int) -> np.ndarray:
    """(H, W) bool: per row, the pixels brighter than the row's median by ``min_contrast`` in runs
    no wider than ``max_width_px`` (painted lines are narrow; a bright sky or a light car is not)."""
    bright = luminance - np.median(luminance, axis=1, keepdims=True) >= min_contrast
    out = np.zeros_like(bright)
    for r, row in enumerate(bright):
        for start, stop in zip(*runs(row), strict=True):
            if stop - start <= max_width_px:
                out[r, start:stop] = True
    return out


def runs(row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs of True in a 1-D bool ``row``: their starts and their stops (exclusive)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], row.astype(np.int8), [0]])))
    return edges[::2], edges[1::2]


def lane_markings(
    image: np.ndarray,
    camera: CameraSpec,
    mount_height: float,
    *,
    band_rows: int,
    min_contrast: float,
    max_width_px: int,
) -> Markings:
    """The markings nearest the ego on each side in the bottom ``band_rows`` rows of ``image``
    ((H, W, 3) uint8 from a forward-looking ``camera``); ``mount_height`` is the LiDAR's above the
    road (camera poses are relative to it)."""
    h = image.shape[0]
    band = image[h - band_rows :].astype(np.float32).mean(axis=-1)
    rows, cols = np.nonzero(marking_peaks(band, min_contrast, max_width_px))
    if not len(rows):
        return Markings(float("nan"), float("nan"), 0.0)
    xy = road_points(camera, mount_height, cols + PIXEL_CENTRE, rows + (h - band_rows) + PIXEL_CENTRE)
    ok = np.isfinite(xy[:, 0]) & (xy[:, 0] > 0)
    rows, xy = rows[ok], xy[ok]
    left, right, near_far = [], [], []
    for r in np.unique(rows):
        y = xy[rows == r, 1]
        x = float(xy[rows == r, 0][0])
        on_left = y[(y > MIN_MARKING_OFFSET_M) & (y < MAX_MARKING_OFFSET_M)]
        on_right = y[(y < -MIN_MARKING_OFFSET_M) & (y > -MAX_MARKING_OFFSET_M)]
        yl = float(on_left.min()) if len(on_left) else np.nan
        yr = float(on_right.max()) if len(on_right) else np.nan
        left.append(yl)
        right.append(yr)
        near_far.append((x, yl, yr))
    yl, yr = _nanmedian(left), _nanmedian(right)
    near_far = [
        (x, a if abs(a - yl) < MARKING_OUTLIER_M else np.nan, b if abs(b - yr) < MARKING_OUTLIER_M else np.nan)
        for x, a, b in near_far
    ]
    return Markings(yl, yr, _lane_heading(near_far))


def _nanmedian(values: list[float]) -> float:
    arr = np.asarray(values, dtype=float)
    return float(np.nanmedian(arr)) if np.isfinite(arr).any() else float("nan")


def _lane_heading(samples: list[tuple[float, float, float]]) -> float:
    """The markings' direction (rad, + left) from a least-squares slope of lateral position over
    distance, pooled over both sides (each side about its own mean); 0 with fewer than two rows."""
    slopes_num, slopes_den = 0.0, 0.0
    for side in (1, 2):
        pts = np.array([(s[0], s[side]) for s in samples if np.isfinite(s[side])])
        if len(pts) < 2:
            continue
        dx = pts[:, 0] - pts[:, 0].mean()
        slopes_num += float((dx * (pts[:, 1] - pts[:, 1].mean())).sum())
        slopes_den += float((dx * dx).sum())
    return float(np.arctan(slopes_num / slopes_den)) if slopes_den > 0 else 0.0
