"""Running episode metrics and the PDM-style score (NAVSIM) computed from SceneFrames.

Per step the env feeds the newest :class:`SceneFrame` and the traffic flags to
:class:`EpisodeMetrics`; it keeps collision / off-road flags, progress, the minimum time-to-collision
to the lead object, and comfort signals (longitudinal acceleration, jerk, yaw rate, lateral
acceleration). :meth:`EpisodeMetrics.summary` turns them into NAVSIM's sub-scores and

    PDMS = NC x DAC x (5 EP + 5 TTC + 2 C) / 12

with NC no-collision (1, or 0 after a collision), DAC drivable-area compliance (0 after leaving the
road), EP ego progress (driven distance relative to driving the whole episode at the road's
speed limit, clipped to [0, 1]; on a road with a ``route``, the log replay's, the fraction of the
route's arc length from the ego's start that the ego covered, measured by projecting it onto the
route), TTC (1 when the time to collision never fell under
``ttc_threshold``), C comfort (1 when every comfort signal stayed inside NAVSIM's bounds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from m4world_env.traffic.polyline import Polyline
from world_model.geometry import world_to_ego_xy
from world_model.scene import SceneFrame

# A route shorter than this (a logged ego that stood still) leaves nothing to cover: progress is 1,
# as NAVSIM scores a scene whose reference progress is below its threshold.
MIN_ROUTE_M = 1.0
# Farther than this from the route (about a lane: the ego left the logged lane) counts as off-route.
ROUTE_TOLERANCE_M = 4.0

# NAVSIM comfort bounds (m/s^2, m/s^3, rad/s).
COMFORT_BOUNDS = {
    "lon_accel_min": -4.05,
    "lon_accel_max": 2.40,
    "lat_accel_abs": 4.89,
    "jerk_abs": 4.13,
    "yaw_rate_abs": 0.95,
}


def time_to_collision(frame: SceneFrame, lateral_margin: float = 0.3, min_turn_radius_m: float = 2.0) -> float:
    """Time until the ego reaches the nearest object ahead in its corridor, at current speeds.

    The corridor follows the ego's current path: a straight line, or, while it turns, the arc of
    radius ``speed / yaw_rate`` (so a car in the lane beside a curve, or oncoming in the next lane
    while the ego turns away, is not "ahead"). Objects count when their footprint overlaps the
    ego's width (+ margin) across the path; distance and closing speed are measured along it.
    Returns ``inf`` when nothing is ahead or the gap is opening.
    """
    ego = frame.ego
    if not frame.objects:
        return float("inf")
    centers = np.array([o.box.center[:2] for o in frame.objects])
    rel = world_to_ego_xy(centers, np.array([ego.x, ego.y]), ego.yaw)
    c, s = np.cos(ego.yaw), np.sin(ego.yaw)
    vel = np.array([o.velocity for o in frame.objects], dtype=float)
    vel = np.stack([vel[:, 0] * c + vel[:, 1] * s, -vel[:, 0] * s + vel[:, 1] * c], axis=1)  # ego frame
    radius = ego.speed / ego.yaw_rate if abs(ego.yaw_rate) > 1e-6 else np.inf
    if abs(radius) < min_turn_radius_m or abs(radius) > 1e4:
        along, across, obj_speed = rel[:, 0], rel[:, 1], vel[:, 0]  # straight path
    else:
        # Turning about (0, radius) in the ego frame (left turns: radius > 0). The point's angle
        # about that centre, from the ego's, in the direction of travel, gives the arc length.
        turn = np.sign(radius)
        to_point = rel - np.array([0.0, radius])
        angle = np.arctan2(to_point[:, 0], -turn * to_point[:, 1])
        dist = np.hypot(to_point[:, 0], to_point[:, 1])
        along, across = angle * abs(radius), dist - abs(radius)
        tangent = turn * np.stack([-to_point[:, 1], to_point[:, 0]], axis=1) / np.maximum(dist, 1e-9)[:, None]
        obj_speed = (vel * tangent).sum(axis=1)
    half_widths = np.array(
        [
            0.5 * max(o.box.size[0], o.box.size[1]) if o.category in ("pedestrian", "cone") else 0.5 * o.box.size[1]
            for o in frame.objects
        ]
    )
    half_lengths = np.array([0.5 * o.box.size[0] for o in frame.objects])
    in_corridor = np.abs(across) < half_widths + 0.5 * ego.size[1] + lateral_margin
    gap = along - half_lengths - 0.5 * ego.size[0]
    ahead = in_corridor & (along > 0)
    if not ahead.any():
        return float("inf")
    closing = ego.speed - obj_speed
    ttc = np.where(ahead & (closing > 1e-3), np.maximum(gap, 0.0) / np.maximum(closing, 1e-3), np.inf)
    return float(ttc.min())


@dataclass
class EpisodeMetrics:
    """Accumulates one episode in O(1) per frame. ``dt`` is the sensor-frame period."""

    dt: float
    reference_speed: float = 30.0
    ttc_threshold: float = 0.9
    route: Polyline | None = None  # our frame; progress is measured along it when given
    route_tolerance_m: float = ROUTE_TOLERANCE_M
    route_start_s: float | None = None
    route_s: float = 0.0
    route_deviation_max: float = 0.0
    steps: int = 0
    frames: int = 0
    collided: bool = False
    off_road: bool = False
    distance: float = 0.0
    min_ttc: float = float("inf")
    ttc_violations: int = 0
    total_reward: float = 0.0
    lon_accel_min: float = 0.0
    lon_accel_max: float = 0.0
    jerk_abs_max: float = 0.0
    yaw_rate_abs_max: float = 0.0
    lat_accel_abs_max: float = 0.0
    _last_xy: tuple[float, float] | None = None
    _last_speed: float | None = None
    _last_accel: float | None = None

    def add_frame(self, frame: SceneFrame) -> None:
        ego = frame.ego
        if self._last_xy is not None:
            self.distance += float(np.hypot(ego.x - self._last_xy[0], ego.y - self._last_xy[1]))
        self._last_xy = (ego.x, ego.y)
        if self.route is not None:
            s, lateral = self.route.project(np.array([[ego.x, ego.y]]))
            self.route_s = float(s[0])
            if self.route_start_s is None:
                self.route_start_s = self.route_s
            self.route_deviation_max = max(self.route_deviation_max, abs(float(lateral[0])))
        if self._last_speed is not None:
            accel = (ego.speed - self._last_speed) / self.dt
            self.lon_accel_min = min(self.lon_accel_min, accel)
            self.lon_accel_max = max(self.lon_accel_max, accel)
            if self._last_accel is not None:
                self.jerk_abs_max = max(self.jerk_abs_max, abs(accel - self._last_accel) / self.dt)
            self._last_accel = accel
        self._last_speed = float(ego.speed)
        self.yaw_rate_abs_max = max(self.yaw_rate_abs_max, abs(float(ego.yaw_rate)))
        self.lat_accel_abs_max = max(self.lat_accel_abs_max, abs(float(ego.speed * ego.yaw_rate)))
        ttc = time_to_collision(frame)
        self.min_ttc = min(self.min_ttc, ttc)
        self.ttc_violations += int(ttc < self.ttc_threshold)
        self.frames += 1

    def add_step(self, reward: float, crashed: bool, on_road: bool) -> None:
        self.steps += 1
        self.total_reward += float(reward)
        self.collided |= bool(crashed)
        self.off_road |= not on_road

    def comfort_signals(self) -> dict[str, float]:
        return {
            "lon_accel_min": self.lon_accel_min,
            "lon_accel_max": self.lon_accel_max,
            "jerk_abs_max": self.jerk_abs_max,
            "yaw_rate_abs_max": self.yaw_rate_abs_max,
            "lat_accel_abs_max": self.lat_accel_abs_max,
        }

    def summary(self) -> dict[str, float]:
        comfort = self.comfort_signals()
        comfortable = (
            comfort["lon_accel_min"] >= COMFORT_BOUNDS["lon_accel_min"]
            and comfort["lon_accel_max"] <= COMFORT_BOUNDS["lon_accel_max"]
            and comfort["jerk_abs_max"] <= COMFORT_BOUNDS["jerk_abs"]
            and comfort["yaw_rate_abs_max"] <= COMFORT_BOUNDS["yaw_rate_abs"]
            and comfort["lat_accel_abs_max"] <= COMFORT_BOUNDS["lat_accel_abs"]
        )
        duration = max(self.frames - 1, 1) * self.dt
        progress = min(self.distance / (self.reference_speed * duration), 1.0)
        route: dict[str, float] = {}
        if self.route is not None:
            progress = self.route_progress()
            route = {
                "route_progress": progress,
                "route_deviation_max_m": self.route_deviation_max,
                "off_route": float(self.route_deviation_max > self.route_tolerance_m),
            }
        nc = 0.0 if self.collided else 1.0
        dac = 0.0 if self.off_road else 1.0
        ttc_ok = 1.0 if self.ttc_violations == 0 else 0.0
        c = 1.0 if comfortable else 0.0
        pdms = nc * dac * (5 * progress + 5 * ttc_ok + 2 * c) / 12
        return {
            "steps": float(self.steps),
            "return": self.total_reward,
            "collision": float(self.collided),
            "off_road": float(self.off_road),
            "distance_m": self.distance,
            "progress": progress,
            "min_ttc_s": self.min_ttc,
            "ttc_violation": 1.0 - ttc_ok,
            "comfort": c,
            **comfort,
            **route,
            "pdms": pdms,
        }

    def route_progress(self) -> float:
        """Fraction of the route's arc length ahead of the ego's start that it covered, in [0, 1]."""
        start = self.route_start_s or 0.0
        remaining = self.route.length - start
        if remaining < MIN_ROUTE_M:
            return 1.0
        return float(np.clip((self.route_s - start) / remaining, 0.0, 1.0))
