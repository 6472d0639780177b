"""Scalar (pure ``math``) versions of highway-env's per-vehicle control formulas.

highway-env evaluates IDM, MOBIL and its lateral controller with numpy on 2-vectors, where
numpy's per-call overhead dominates. The mixins below override only the numeric leaf methods,
with the same formulas and constants, so the decisions are highway-env's; ``act``,
``change_lane_policy`` and ``mobil`` are highway-env's own code calling these.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from highway_env.road.lane import AbstractLane, CircularLane, SineLane, StraightLane
from highway_env.vehicle.kinematics import Vehicle

if TYPE_CHECKING:
    from highway_env.road.road import LaneIndex
    from highway_env.vehicle.objects import RoadObject


def not_zero(x: float, eps: float = 1e-2) -> float:
    """highway-env's utils.not_zero."""
    if abs(x) > eps:
        return x
    return eps if x >= 0 else -eps


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def local_xy(lane: AbstractLane, x: float, y: float) -> tuple[float, float]:
    """``lane.local_coordinates`` for one point, without numpy."""
    if isinstance(lane, StraightLane):
        sx, sy = lane.start
        dx, dy = lane.direction
        ex, ey = x - sx, y - sy
        s = ex * dx + ey * dy
        r = -ex * dy + ey * dx
        if isinstance(lane, SineLane):
            r -= lane.amplitude * math.sin(lane.pulsation * s + lane.phase)
        return float(s), float(r)
    if isinstance(lane, CircularLane):
        cx, cy = lane.center
        ex, ey = x - cx, y - cy
        phi = lane.start_phase + wrap(math.atan2(ey, ex) - lane.start_phase)
        return (
            float(lane.direction * (phi - lane.start_phase) * lane.radius),
            float(lane.direction * (lane.radius - math.hypot(ex, ey))),
        )
    s, r = lane.local_coordinates((x, y))
    return float(s), float(r)


def heading_at(lane: AbstractLane, s: float) -> float:
    if isinstance(lane, SineLane):
        return float(
            lane.heading + math.atan(lane.amplitude * lane.pulsation * math.cos(lane.pulsation * s + lane.phase))
        )
    if isinstance(lane, StraightLane):
        return float(lane.heading)
    if isinstance(lane, CircularLane):
        return float(lane.direction * s / lane.radius + lane.start_phase + math.pi / 2 * lane.direction)
    return float(lane.heading_at(s))


class FastControlMixin:
    """ControlledVehicle/RoadObject leaf methods in scalar math (same formulas)."""

    def lane_distance_to(self, other: RoadObject | None, lane: AbstractLane | None = None) -> float:
        if not other:
            return math.nan
        lane = lane or self.lane
        return local_xy(lane, *other.position)[0] - local_xy(lane, *self.position)[0]

    def follow_road(self) -> None:
        lane = self.road.network.get_lane(self.target_lane_index)
        s = local_xy(lane, *self.position)[0]
        if s > lane.length - lane.VEHICLE_LENGTH / 2:  # AbstractLane.after_end
            self.target_lane_index = self.road.network.next_lane(
                self.target_lane_index,
                route=self.route,
                position=self.position,
                np_random=self.road.np_random,
            )

    def steering_control(self, target_lane_index: LaneIndex) -> float:
        lane = self.road.network.get_lane(target_lane_index)
        s, r = local_xy(lane, *self.position)
        future_heading = heading_at(lane, s + self.speed * self.TAU_PURSUIT)
        lateral_speed_command = -self.KP_LATERAL * r
        heading_command = math.asin(clip(lateral_speed_command / not_zero(self.speed), -1, 1))
        heading_ref = future_heading + clip(heading_command, -math.pi / 4, math.pi / 4)
        heading_rate_command = self.KP_HEADING * wrap(heading_ref - self.heading)
        slip = math.asin(clip(self.LENGTH / 2 / not_zero(self.speed) * heading_rate_command, -1, 1))
        steering = math.atan(2 * math.tan(slip))
        return clip(steering, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE)

    def step(self, dt: float) -> None:
        """Vehicle.step (kinematic bicycle) in scalar math."""
        self.clip_actions()
        beta = math.atan(0.5 * math.tan(self.action["steering"]))
        pos = self.position
        pos[0] += self.speed * math.cos(self.heading + beta) * dt
        pos[1] += self.speed * math.sin(self.heading + beta) * dt
        if self.impact is not None:
            self.position = pos + self.impact
            self.crashed = True
            self.impact = None
        self.heading += self.speed * math.sin(beta) / (self.LENGTH / 2) * dt
        self.speed += self.action["acceleration"] * dt
        self.on_state_update()


class FastIDMMixin(FastControlMixin):
    """IDMVehicle.act / step / acceleration / desired_gap in scalar math (same formulas)."""

    def step(self, dt: float) -> None:
        self.timer += dt  # IDMVehicle.step
        super().step(dt)

    def act(self, action: dict | str | None = None) -> None:
        """IDMVehicle.act: MOBIL lane choice, lateral control, IDM on current and target lane."""
        if self.crashed:
            return
        self.follow_road()
        if self.enable_lane_change:
            self.change_lane_policy()
        steering = clip(
            self.steering_control(self.target_lane_index), -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE
        )
        front, rear = self.road.neighbour_vehicles(self, self.lane_index)
        acc = self.acceleration(ego_vehicle=self, front_vehicle=front, rear_vehicle=rear)
        if self.lane_index != self.target_lane_index:
            front, rear = self.road.neighbour_vehicles(self, self.target_lane_index)
            acc = min(acc, self.acceleration(ego_vehicle=self, front_vehicle=front, rear_vehicle=rear))
        self.action = {"steering": steering, "acceleration": clip(acc, -self.ACC_MAX, self.ACC_MAX)}

    def acceleration(
        self,
        ego_vehicle: RoadObject | None = None,
        front_vehicle: RoadObject | None = None,
        rear_vehicle: RoadObject | None = None,
    ) -> float:
        if not ego_vehicle or not isinstance(ego_vehicle, Vehicle):
            return 0
        target = getattr(ego_vehicle, "target_speed", 0)
        if ego_vehicle.lane and ego_vehicle.lane.speed_limit is not None:
            target = clip(target, 0, ego_vehicle.lane.speed_limit)
        acc = self.COMFORT_ACC_MAX * (1 - (max(ego_vehicle.speed, 0) / abs(not_zero(target))) ** self.DELTA)
        if front_vehicle:
            d = ego_vehicle.lane_distance_to(front_vehicle)
            acc -= self.COMFORT_ACC_MAX * (self.desired_gap(ego_vehicle, front_vehicle) / not_zero(d)) ** 2
        return acc

    def desired_gap(
        self, ego_vehicle: Vehicle, front_vehicle: RoadObject | None = None, projected: bool = True
    ) -> float:
        ab = -self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN
        if projected:  # (v_ego - v_front) . direction_ego
            dv = ego_vehicle.speed - front_vehicle.speed * math.cos(front_vehicle.heading - ego_vehicle.heading)
        else:
            dv = ego_vehicle.speed - front_vehicle.speed
        return (
            self.DISTANCE_WANTED + ego_vehicle.speed * self.TIME_WANTED + ego_vehicle.speed * dv / (2 * math.sqrt(ab))
        )
