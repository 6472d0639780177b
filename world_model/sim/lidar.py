"""The LiDAR: exact ray casting against the road plane and every object's full 3D box.

Rays follow :class:`~world_model.sensors.LidarSpec` (row 0 = top beam, column 0 = azimuth +180 deg,
decreasing). The road returns are fixed per beam and precomputed. For objects, each box is culled
to the azimuth sector and elevation band that can possibly hit it; all (ray, box) candidate pairs
of a frame are then intersected in one vectorized slab test. The ego's own body is not modelled,
and a box that contains the LiDAR (a crash) returns nothing: rays leave it from the inside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from world_model.sensors import LidarSpec
from world_model.sim.poses import ObjectPoses


@dataclass(frozen=True)
class LidarRays:
    """Per-spec precomputation."""

    directions: np.ndarray  # (beams * azimuth, 3) float32 unit rays, row-major
    ground: np.ndarray  # (beams, azimuth) float32 range to the road, inf when none within max_range
    elevations: np.ndarray  # (beams,) radians, top first
    az_step: float  # radians between columns


def lidar_rays(spec: LidarSpec) -> LidarRays:
    if spec.beams < 1 or spec.azimuth < 1:
        raise ValueError(f"LidarSpec needs beams >= 1 and azimuth >= 1, got {spec.beams}x{spec.azimuth}")
    el = spec.elevations()
    sin_el = np.sin(el)
    with np.errstate(divide="ignore"):
        r = np.where(sin_el < 0, spec.mount_height / np.where(sin_el < 0, -sin_el, 1.0), np.inf)
    r = np.where(r <= spec.max_range, r, np.inf)
    return LidarRays(
        directions=spec.ray_directions().reshape(-1, 3).astype(np.float32),
        ground=np.broadcast_to(r[:, None], (spec.beams, spec.azimuth)).astype(np.float32),
        elevations=el,
        az_step=2.0 * math.pi / spec.azimuth,
    )


def _candidate_bands(
    poses: ObjectPoses, spec: LidarSpec, rays: LidarRays, margin: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per object: ray origin in the box frame, half size, yaw cos/sin, first row, rows, first col, cols."""
    centre, half = poses.centre, poses.half
    c, s = poses.cos, poses.sin
    n = len(centre)
    origin = -np.stack([c * centre[:, 0] + s * centre[:, 1], -s * centre[:, 0] + c * centre[:, 1], centre[:, 2]], 1)
    gap = np.maximum(np.abs(origin) - half, 0.0)
    dmin = np.hypot(gap[:, 0], gap[:, 1])  # horizontal distance from the LiDAR to the footprint
    reachable = np.hypot(dmin, gap[:, 2]) <= spec.max_range
    surrounds = dmin <= 0.0

    # Azimuth sector: attained at the footprint's corners when the LiDAR is outside it.
    corners = poses.corners[:, [0, 1, 5, 4]]  # the top face: the footprint's four corners
    az_c = np.arctan2(centre[:, 1], centre[:, 0])
    spread = (np.arctan2(corners[..., 1], corners[..., 0]) - az_c[:, None] + np.pi) % (2 * np.pi) - np.pi
    a = spec.azimuth
    j0 = np.ceil((np.pi - az_c - spread.max(1)) / rays.az_step).astype(np.int64) - margin
    j1 = np.floor((np.pi - az_c - spread.min(1)) / rays.az_step).astype(np.int64) + margin
    ncol = np.where(surrounds, a, np.minimum(j1 - j0 + 1, a))
    j0 = np.where(surrounds, 0, j0)

    # Elevation band: no point of the box is nearer than dmin horizontally.
    z_top, z_bot = centre[:, 2] + half[:, 2], centre[:, 2] - half[:, 2]
    safe = np.where(surrounds, 1.0, dmin)
    el_hi = np.where(surrounds, np.pi / 2, np.arctan2(z_top, safe))
    el_lo = np.where(surrounds, -np.pi / 2, np.arctan2(z_bot, safe))
    el = rays.elevations
    if len(el) == 1:
        inside = (el[0] >= el_lo) & (el[0] <= el_hi)
        i0, nrow = np.zeros(n, np.int64), inside.astype(np.int64)
    else:
        step = (el[0] - el[-1]) / (len(el) - 1)
        i0 = np.clip(np.ceil((el[0] - el_hi) / step - 1e-9), 0, len(el)).astype(np.int64)
        i1 = np.clip(np.floor((el[0] - el_lo) / step + 1e-9), -1, len(el) - 1).astype(np.int64)
        nrow = np.maximum(i1 - i0 + 1, 0)
    nrow = np.where(reachable, nrow, 0)
    return origin, half, c, s, i0, nrow, j0 % a, ncol


def cast(poses: ObjectPoses, spec: LidarSpec, rays: LidarRays, margin_cols: int) -> np.ndarray:
    """(beams, azimuth) float32 range map; ``spec.no_return`` where nothing is hit within max_range."""
    ranges = rays.ground.copy()
    if len(poses.centre):
        origin, half, c, s, i0, nrow, j0, ncol = _candidate_bands(poses, spec, rays, margin_cols)
        per = nrow * ncol
        total = int(per.sum())
        if total:
            obj = np.repeat(np.arange(len(per)), per)
            k = np.arange(total) - np.repeat(np.cumsum(per) - per, per)
            nc = ncol[obj]
            row = i0[obj] + k // nc
            col = (j0[obj] + k % nc) % spec.azimuth
            flat = row * spec.azimuth + col
            d = rays.directions[flat]
            co, so = c[obj].astype(np.float32), s[obj].astype(np.float32)
            local = (co * d[:, 0] + so * d[:, 1], -so * d[:, 0] + co * d[:, 1], d[:, 2])
            o = origin[obj].astype(np.float32)
            hh = half[obj].astype(np.float32)
            t_near = np.zeros(total, dtype=np.float32)
            t_far = np.full(total, np.inf, dtype=np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                for ax in range(3):
                    inv = 1.0 / local[ax]
                    t1 = (-hh[:, ax] - o[:, ax]) * inv
                    t2 = (hh[:, ax] - o[:, ax]) * inv
                    t_near = np.fmax(t_near, np.fmin(t1, t2))
                    t_far = np.fmin(t_far, np.fmax(t1, t2))
            hit = (t_near <= t_far) & (t_near > 0)
            out = ranges.reshape(-1)
            np.minimum.at(out, flat[hit], t_near[hit])
    ranges[ranges > spec.max_range] = spec.no_return
    return ranges
