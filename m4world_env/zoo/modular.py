"""Modular sensor policies: LiDAR gap keeping (IDM on the measured gap) and camera lane centring.

    x_gap  = nearest obstacle return ahead in the ego's corridor        (perception.forward_gap)
    dv     = -(x_gap(t) - x_gap(t - 1)) / dt                           closing speed, smoothed
    s*     = s0 + v T + v dv / (2 sqrt(a b))
    a      = a_max (1 - (v / v0)^4 - (s* / s)^2)                        s = x_gap - half the ego's length
    y_t    = y_lane + L_d tan(psi_lane)                                 the lane centre L_d ahead
    delta  = -atan(k 2 y_t L / L_d^2)                                   pure pursuit; + turns right

IDM is highway-env's (Treiber et al.); the steering is pure pursuit on a bicycle of wheelbase ``L``
toward the lane centre the FRONT camera's markings give (:func:`perception.lane_markings`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from m4world_env.zoo.base import EgoStatus, SensorGeometry, SensorPolicy
from m4world_env.zoo.perception import beam_band, forward_gap, lane_markings

# highway-env's vehicle: 5 m long; the LiDAR sits at its centre, so the gap to a return ahead is
# the return's distance less half the length.
EGO_HALF_LENGTH_M = 2.5
WHEELBASE_M = 5.0  # highway-env's bicycle model steers about the vehicle's length
STEERING_LIMIT_RAD = math.pi / 6  # a pure-pursuit command beyond this is a misread, not a curve
# A gap that moves more than this in one step is a new object in the corridor, not closing speed.
GAP_JUMP_M = 5.0
CLOSING_SMOOTHING = 0.5  # exponential smoothing of the measured closing speed (per step)
LANE_MEMORY_STEPS = 5  # hold the last seen lane centre this many steps when the markings vanish


@dataclass(frozen=True)
class GapKeeping:
    """IDM on the LiDAR gap. ``beams_deg``: the elevation band read; ``half_width_m``: the corridor."""

    cruise_speed: float = 25.0  # v0, m/s
    time_headway: float = 1.5  # T, s
    min_gap: float = 5.0  # s0, m
    max_accel: float = 1.5  # a_max, m/s^2
    comfort_decel: float = 3.0  # b, m/s^2
    max_brake: float = 5.0  # the strongest braking it commands, m/s^2
    # The most the command changes in one policy step, m/s^2: the env applies a command at once, so
    # a larger change is a jerk past NAVSIM's comfort bound (4.13 m/s^3 over a 0.1 s frame).
    accel_change: float = 0.4
    beams_deg: tuple[float, float] = (-15.0, 2.0)
    half_width_m: float = 1.3
    enabled: bool = True  # False: cruise at v0 whatever is ahead


@dataclass(frozen=True)
class LaneCentring:
    """Pure pursuit toward the lane centre seen in ``view``; ``gain`` 0 holds the wheel straight."""

    gain: float = 1.0
    lookahead_s: float = 0.8  # L_d = max(min_lookahead_m, v * lookahead_s)
    min_lookahead_m: float = 8.0
    view: str = "FRONT"
    band_rows: int = 20  # the bottom rows of the view read: the road 4-10 m ahead at 64 rows
    min_contrast: float = 18.0  # grey levels above the row's median
    max_width_px: int = 6
    smoothing: float = 0.5  # share of the new command taken each step (1: none)


class ModularDriver(SensorPolicy):
    """Gap keeping on the LiDAR and lane centring on a camera (see the module docstring)."""

    def __init__(self, geometry: SensorGeometry, gap: GapKeeping, lane: LaneCentring) -> None:
        super().__init__(geometry)
        self.gap, self.lane = gap, lane
        self._beams = beam_band(geometry.lidar, *gap.beams_deg)
        self._camera_index = geometry.view_index(lane.view)
        self._camera = geometry.rig.cameras[self._camera_index]
        self._last_gap = math.inf
        self._closing = 0.0
        self._accel, self._steer = 0.0, 0.0
        self._lane_centre, self._lane_heading, self._lane_age = 0.0, 0.0, LANE_MEMORY_STEPS + 1

    def drive(self, obs: Mapping[str, np.ndarray], status: EgoStatus) -> np.ndarray:
        wanted = self.acceleration(obs["lidar"], status.speed)
        limit = self.gap.accel_change
        # Braking harder than the comfort bound is safety: it is never delayed by the rate limit.
        if wanted > -self.gap.comfort_decel:
            wanted = float(np.clip(wanted, self._accel - limit, self._accel + limit))
        self._accel = wanted
        target = self.steering(obs["cameras"][self._camera_index], status.speed)
        self._steer += self.lane.smoothing * (target - self._steer)
        return self.geometry.action(self._accel, self._steer)

    def acceleration(self, ranges: np.ndarray, speed: float) -> float:
        g, v = self.gap, max(speed, 0.0)
        free = g.max_accel * (1.0 - (v / g.cruise_speed) ** 4)
        if not g.enabled:
            return float(np.clip(free, -g.max_brake, g.max_accel))
        x = forward_gap(ranges, self.geometry.lidar, half_width_m=g.half_width_m, beams=self._beams)
        if math.isfinite(x) and math.isfinite(self._last_gap) and abs(x - self._last_gap) < GAP_JUMP_M:
            measured = (self._last_gap - x) / self.geometry.step_seconds
            self._closing += CLOSING_SMOOTHING * (measured - self._closing)
        else:
            self._closing = 0.0
        self._last_gap = x
        if not math.isfinite(x):
            return float(np.clip(free, -g.max_brake, g.max_accel))
        s = max(x - EGO_HALF_LENGTH_M, 0.1)
        wanted = g.min_gap + v * g.time_headway + v * self._closing / (2.0 * math.sqrt(g.max_accel * g.comfort_decel))
        accel = free - g.max_accel * (max(wanted, 0.0) / s) ** 2
        return float(np.clip(accel, -g.max_brake, g.max_accel))

    def steering(self, image: np.ndarray, speed: float) -> float:
        ln = self.lane
        if ln.gain == 0.0:
            return 0.0
        seen = lane_markings(
            image,
            self._camera,
            self.geometry.lidar.mount_height,
            band_rows=ln.band_rows,
            min_contrast=ln.min_contrast,
            max_width_px=ln.max_width_px,
        )
        centre = seen.centre_m
        if math.isfinite(centre):
            self._lane_centre, self._lane_heading, self._lane_age = centre, seen.heading, 0
        else:
            self._lane_age += 1
        if self._lane_age > LANE_MEMORY_STEPS:
            return 0.0
        lookahead = max(ln.min_lookahead_m, max(speed, 0.0) * ln.lookahead_s)
        target = self._lane_centre + lookahead * math.tan(self._lane_heading)
        steer = -math.atan(ln.gain * 2.0 * target * WHEELBASE_M / lookahead**2)
        return float(np.clip(steer, -STEERING_LIMIT_RAD, STEERING_LIMIT_RAD))
