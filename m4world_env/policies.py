"""Reference driving policies that read the traffic bridge's state.

Every policy is a callable ``policy(state) -> action`` where ``state`` is a
:class:`~m4world_env.traffic.TrafficBridge`, any object with a ``.bridge`` attribute (e.g. the
Gymnasium env), or a dict with a ``"bridge"`` entry (e.g. an env's ``info``). The action matches
the bridge's ``action_type``: a float32 ``[acceleration, steering]`` in [-1, 1] (highway-env's
ContinuousAction meaning: steering +1 turns right) or an int meta-action 0..4.

* :class:`IDMAutopilot`: IDM speed control + MOBIL-style lane changes, with optional seeded
  random lane/speed changes so that recorded data is varied (:data:`DRIVING_STYLES`).
* :class:`ConstantSpeedLaneKeeping`: holds a speed and the current lane.
* :class:`RandomPolicy`: uniformly random actions (seeded).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle

from m4world_env.traffic import TrafficBridge
from m4world_env.traffic.actions import META_INDEX
from m4world_env.traffic.fastmath import clip, heading_at, local_xy, not_zero, wrap

if TYPE_CHECKING:
    from highway_env.vehicle.kinematics import Vehicle


def bridge_of(state: object) -> TrafficBridge:
    """The bridge behind ``state`` (a bridge, an object with ``.bridge``, or ``{"bridge": ...}``)."""
    if isinstance(state, TrafficBridge):
        return state
    if isinstance(state, dict) and isinstance(state.get("bridge"), TrafficBridge):
        return state["bridge"]
    if isinstance(getattr(state, "bridge", None), TrafficBridge):
        return state.bridge
    raise TypeError(
        f"a policy needs a TrafficBridge, an object with .bridge, or a dict with 'bridge'; got {type(state).__name__}"
    )


def lane_keeping_steering(bridge: TrafficBridge, lane_index: tuple[str, str, int]) -> float:
    """highway-env's ControlledVehicle lateral controller towards ``lane_index``: a steering
    angle in highway-env's convention (radians, positive = right)."""
    v, c = bridge.ego_vehicle, ControlledVehicle
    lane = bridge.road.network.get_lane(lane_index)
    s, r = local_xy(lane, *v.position)
    future = heading_at(lane, s + v.speed * c.TAU_PURSUIT)
    heading_cmd = math.asin(clip(-c.KP_LATERAL * r / not_zero(v.speed), -1, 1))
    rate = c.KP_HEADING * wrap(future + clip(heading_cmd, -math.pi / 4, math.pi / 4) - v.heading)
    slip = math.asin(clip(v.LENGTH / 2 / not_zero(v.speed) * rate, -1, 1))
    return math.atan(2 * math.tan(slip))


class RoadFollower:
    """Keeps the lane a policy tracks, moving it along the bridge's route at each lane's end
    (highway-env's ControlledVehicle.follow_road). Resets itself when a new episode starts."""

    def __init__(self) -> None:
        self.target: tuple[str, str, int] | None = None
        self._time = math.inf

    def __call__(self, bridge: TrafficBridge) -> tuple[str, str, int]:
        v, net = bridge.ego_vehicle, bridge.road.network
        if self.target is None or bridge.time < self._time:
            self.target = v.lane_index
        self._time = bridge.time
        lane = net.get_lane(self.target)
        if local_xy(lane, *v.position)[0] > lane.length - lane.VEHICLE_LENGTH / 2:
            edges = [r[:2] for r in bridge.route]
            route = bridge.route[edges.index(self.target[:2]) + 1 :] if self.target[:2] in edges else None
            self.target = net.next_lane(self.target, route=route, position=v.position, np_random=bridge.road.np_random)
        return self.target


def _continuous(bridge: TrafficBridge, acceleration: float, steering: float) -> np.ndarray:
    cfg = bridge.config.actions
    a = 2 * (acceleration - cfg.acceleration_range[0]) / (cfg.acceleration_range[1] - cfg.acceleration_range[0]) - 1
    st = 2 * (steering - cfg.steering_range[0]) / (cfg.steering_range[1] - cfg.steering_range[0]) - 1
    return np.array([clip(a, -1.0, 1.0), clip(st, -1.0, 1.0)], dtype=np.float32)


@dataclass(frozen=True)
class AutopilotConfig:
    """IDM/MOBIL constants default to highway-env's IDMVehicle; the random parts are for data."""

    comfort_acc: float = IDMVehicle.COMFORT_ACC_MAX
    comfort_dec: float = -IDMVehicle.COMFORT_ACC_MIN
    distance_wanted: float = IDMVehicle.DISTANCE_WANTED
    time_wanted: float = IDMVehicle.TIME_WANTED
    delta: float = IDMVehicle.DELTA
    lane_change_gain: float = IDMVehicle.LANE_CHANGE_MIN_ACC_GAIN
    max_braking_imposed: float = IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED
    speed_fraction: float = 0.9  # desired speed as a fraction of the lane's limit
    random_lane_change_prob: float = 0.0  # per call: try a random (safe) lane change
    random_speed_change_prob: float = 0.0  # per call: redraw the desired speed
    speed_fraction_range: tuple[float, float] = (0.6, 1.0)  # for the redraw
    speed_tolerance: float = 1.0  # m/s dead band before a discrete FASTER/SLOWER
    lane_change_cooldown_s: float = 2 * IDMVehicle.LANE_CHANGE_DELAY  # no new lane change before this


# Ego driving styles for recorded data: the autopilot with seeded random manoeuvres, so that the
# ego's actions have consequences in the sensors (the road ahead closing in under braking, the
# scene sliding sideways in a lane change) for a world model to learn. The policy runs at the
# scenario's policy frequency (5 Hz in the bundled scenarios): a probability of 0.08 per call is
# a new desired speed every 2.5 s on average.
DRIVING_STYLES: dict[str, AutopilotConfig] = {
    # IDM speed keeping; MOBIL lane changes only where they pay off.
    "steady": AutopilotConfig(),
    # Brakes to as low as 20% of the limit and accelerates back to above it.
    "speed_changes": AutopilotConfig(random_speed_change_prob=0.08, speed_fraction_range=(0.2, 1.1)),
    # Frequent random lane changes, accepting gaps that make the new follower brake at up to
    # 4 m/s^2 (the default 2 m/s^2 leaves almost no gap in the scenarios' randomized traffic).
    "lane_changes": AutopilotConfig(random_lane_change_prob=0.15, max_braking_imposed=4.0),
    # Changes lanes back and forth whenever a gap allows, with speed changes.
    "weaving": AutopilotConfig(
        random_lane_change_prob=0.5,
        max_braking_imposed=4.0,
        random_speed_change_prob=0.05,
        speed_fraction_range=(0.5, 1.1),
    ),
}


def driving_style(name: str) -> AutopilotConfig:
    """The autopilot settings of style ``name`` (one of :data:`DRIVING_STYLES`)."""
    try:
        return DRIVING_STYLES[name]
    except KeyError:
        raise ValueError(f"unknown driving style {name!r}; choose from {sorted(DRIVING_STYLES)}") from None


class IDMAutopilot:
    """IDM longitudinal control and MOBIL lane choice for the ego, for either action type."""

    def __init__(self, config: AutopilotConfig = AutopilotConfig(), seed: int | None = None) -> None:
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.speed_fraction = config.speed_fraction
        self._last_change = -math.inf
        self._road = RoadFollower()

    def _idm(self, v: Vehicle | None, front: Vehicle | None, desired: float) -> float:
        """IDM acceleration of ``v`` (a highway-env vehicle) behind ``front`` (or free road)."""
        c = self.config
        if v is None:
            return 0.0
        acc = c.comfort_acc * (1 - (max(v.speed, 0) / not_zero(desired)) ** c.delta)
        if front is not None:
            d = v.lane_distance_to(front)
            dv = v.speed - front.speed * math.cos(front.heading - v.heading)
            gap = (
                c.distance_wanted
                + v.speed * c.time_wanted
                + v.speed * dv / (2 * math.sqrt(c.comfort_acc * c.comfort_dec))
            )
            acc -= c.comfort_acc * (gap / not_zero(d)) ** 2
        return acc

    def _choose_lane(self, b: TrafficBridge, desired: float) -> tuple[str, str, int]:
        ego, road, c = b.ego_vehicle, b.road, self.config
        current = self._road(b)
        front, _ = road.neighbour_vehicles(ego, current)
        a_here = self._idm(ego, front, desired)
        if b.time - self._last_change < c.lane_change_cooldown_s:
            return current
        safe, gains = [], {}
        for idx in road.network.side_lanes(current):
            if not road.network.get_lane(idx).is_reachable_from(ego.position):
                continue
            new_front, new_rear = road.neighbour_vehicles(ego, idx)
            rear_desired = getattr(new_rear, "target_speed", desired)
            if new_rear is not None and self._idm(new_rear, ego, rear_desired) < -c.max_braking_imposed:
                continue  # the new follower would have to brake hard
            if self._idm(ego, new_front, desired) < -c.max_braking_imposed:
                continue  # we would have to brake hard behind the new leader
            safe.append(idx)
            gains[idx] = self._idm(ego, new_front, desired) - a_here
        if safe and self.rng.random() < c.random_lane_change_prob:
            choice = safe[int(self.rng.integers(len(safe)))]
        else:
            best = max(safe, key=lambda i: gains[i], default=None)
            choice = best if best is not None and gains[best] >= c.lane_change_gain else current
        if choice != current:
            self._last_change = b.time
        return choice

    def __call__(self, state: object) -> np.ndarray | int:
        b = bridge_of(state)
        c, ego = self.config, b.ego_vehicle
        if self.rng.random() < c.random_speed_change_prob:
            self.speed_fraction = float(self.rng.uniform(*c.speed_fraction_range))
        desired = self.speed_fraction * (ego.lane.speed_limit or ego.speed)
        if b.action_type == "discrete_meta":
            if ego.lane_index != ego.target_lane_index:  # a lane change is under way
                return META_INDEX["IDLE"]
            target = self._choose_lane(b, desired)
            if target[2] != ego.lane_index[2]:
                return META_INDEX["LANE_LEFT"] if target[2] < ego.lane_index[2] else META_INDEX["LANE_RIGHT"]
            front, _ = b.road.neighbour_vehicles(ego, ego.lane_index)
            if self._idm(ego, front, desired) < -c.comfort_acc / 2 or ego.target_speed > desired + c.speed_tolerance:
                return META_INDEX["SLOWER"]
            if ego.target_speed < desired - c.speed_tolerance:
                return META_INDEX["FASTER"]
            return META_INDEX["IDLE"]
        target = self._choose_lane(b, desired)
        self._road.target = target
        front, _ = b.road.neighbour_vehicles(ego, ego.lane_index)
        acc = self._idm(ego, front, desired)
        if target != ego.lane_index:
            acc = min(acc, self._idm(ego, b.road.neighbour_vehicles(ego, target)[0], desired))
        return _continuous(b, acc, lane_keeping_steering(b, target))


@dataclass(frozen=True)
class LaneKeepingConfig:
    speed_gain: float = 1.0 / ControlledVehicle.TAU_ACC  # highway-env's speed controller gain, 1/s


class ConstantSpeedLaneKeeping:
    """Holds ``speed`` (default: the ego's speed at the first call) and its current lane."""

    def __init__(self, speed: float | None = None, config: LaneKeepingConfig = LaneKeepingConfig()) -> None:
        self.speed, self.config = speed, config
        self._road = RoadFollower()

    def __call__(self, state: object) -> np.ndarray | int:
        b = bridge_of(state)
        if self.speed is None:
            self.speed = float(b.ego_vehicle.speed)
        if b.action_type == "discrete_meta":
            return META_INDEX["IDLE"]  # MDPVehicle already holds its lane and target speed
        acc = self.config.speed_gain * (self.speed - b.ego_vehicle.speed)
        return _continuous(b, acc, lane_keeping_steering(b, self._road(b)))


class RandomPolicy:
    """Uniform random actions from a seeded generator."""

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, state: object) -> np.ndarray | int:
        b = bridge_of(state)
        if b.action_type == "discrete_meta":
            return int(self.rng.integers(len(META_INDEX)))
        return self.rng.uniform(-1.0, 1.0, size=2).astype(np.float32)
