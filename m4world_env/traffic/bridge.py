"""TrafficBridge: a scenario's highway-env traffic, stepped by ego actions, seen as SceneFrames.

One ``step(action)`` is one policy step: the action is applied once, then the road runs
``frames_per_step`` sensor frames of ``substeps`` simulation steps each, and one
:class:`world_model.SceneFrame` is emitted per sensor frame. highway-env's frame (y right,
heading clockwise) becomes ours with ``(x, -y)``, ``yaw = -heading``; boxes stand on z = 0.

Every random choice comes from generators seeded by ``reset(seed)`` (highway-env's ``road.np_random``
included), never from the global numpy RNG, so the same seed gives identical frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from m4world_env.scenario import Scenario, ScenarioError, scenario_from_dict
from m4world_env.traffic import population
from m4world_env.traffic.actions import (
    ACTION_TYPES,
    ActionConfig,
    ActionError,
    continuous_controls,
    meta_action,
)
from m4world_env.traffic.mapgeom import MapSamplingConfig, extract_map
from m4world_env.traffic.objects import ScriptedObject
from m4world_env.traffic.polyline import points_in_polygons
from m4world_env.traffic.roads import build_road
from m4world_env.traffic.sim import EgoMetaVehicle, EgoVehicle, FastRoad, TrafficVehicle, size_object
from world_model.scene import CATEGORY_SIZES, Box3D, EgoState, MapGeometry, SceneFrame, SceneObject
from world_model.sensors import BevSpec, CameraRig, LidarSpec, default_rig


@dataclass(frozen=True)
class BridgeConfig:
    frame_radius_m: float = 200.0  # objects farther than this from the ego are left out of frames
    ego_category: str = "car"  # the ego's footprint comes from CATEGORY_SIZES[ego_category]
    actions: ActionConfig = ActionConfig()
    map_sampling: MapSamplingConfig = MapSamplingConfig()
    population: population.PopulationConfig = population.PopulationConfig()


def check_reset(scenario: Scenario, source: str) -> None:
    """Build what ``reset`` builds (road, ego, scripted objects, traffic) once, so that a scenario
    that passes ``m4world scenarios --check`` never fails at reset. Raises :class:`ScenarioError`."""
    try:
        TrafficBridge(scenario).reset(seed=0)
    except ScenarioError:
        raise
    except (ValueError, ArithmeticError, IndexError, KeyError, MemoryError) as e:
        raise ScenarioError(f"{source}: the scenario validates but its road or traffic cannot be built: {e!r}") from e


class TrafficBridge:
    """highway-env road + IDM/MOBIL traffic + scripted objects + ego, emitting SceneFrames."""

    def __init__(
        self,
        scenario: Scenario,
        action_type: str = "continuous",
        rig: CameraRig | None = None,
        lidar: LidarSpec | None = None,
        bev: BevSpec | None = None,
        config: BridgeConfig = BridgeConfig(),
    ) -> None:
        if action_type not in ACTION_TYPES:
            raise ActionError(f"action_type must be one of {ACTION_TYPES}, got {action_type!r}")
        # model_copy(update=...) does not validate: re-validate so that updates given as plain
        # dicts (e.g. traffic={"count": 0}) become models and bad values fail here, by name.
        self.scenario = scenario_from_dict(scenario.model_dump(by_alias=True, warnings=False), scenario.name)
        self.action_type = action_type
        self.config = config
        self.rig = rig if rig is not None else default_rig()
        self.lidar = lidar if lidar is not None else LidarSpec()
        self.bev = bev if bev is not None else BevSpec()
        self.prompt = scenario.prompt()
        self._map: MapGeometry | None = None
        self.road: FastRoad | None = None

    # ------------------------------------------------------------------ lifecycle

    @property
    def frames_per_step(self) -> int:
        return self.scenario.frames_per_step

    def reset(self, seed: int | None = None) -> SceneFrame:
        """Build road, ego, scripted objects and IDM traffic; return frame 0."""
        s = self.scenario
        road_seed, traffic_seed = np.random.SeedSequence(seed).spawn(2)
        self.layout = build_road(s.road, s.ego.turn)
        self.road = FastRoad(self.layout.network, np.random.default_rng(road_seed))
        self._traffic_rng = np.random.default_rng(traffic_seed)
        if self._map is None:  # the road never changes for a bridge: one map object for all frames
            drawn = self.layout.map
            self._map = drawn if drawn is not None else extract_map(self.layout, self.config.map_sampling)
        self.ego_vehicle = self._make_ego()
        self.road.vehicles.append(self.ego_vehicle)
        self._ids: dict[str, TrafficVehicle | ScriptedObject] = {}
        for spec in s.objects:
            self._add(population.make_scripted(self.road, self.layout, spec, s.name))
        for v in population.spawn_traffic(self.road, self.layout, s, self._traffic_rng, self.config.population):
            self._add(v)
        self._substeps = 0
        self.frame_index = 0
        self._prev_heading = self.ego_vehicle.heading
        self.road.invalidate()
        return self._frame()

    def _make_ego(self) -> EgoVehicle | EgoMetaVehicle:
        s, net = self.scenario, self.layout.network
        frm, to = self.layout.ego_edge
        lane = net.get_lane((frm, to, s.ego.lane))
        pos, heading = lane.position(s.ego.longitudinal, 0.0), lane.heading_at(s.ego.longitudinal)
        if self.action_type == "continuous":
            ego = EgoVehicle(self.road, pos, heading, s.ego.speed)
        else:
            speeds = self.config.actions.target_speeds(lane.speed_limit)
            ego = EgoMetaVehicle(self.road, pos, heading, s.ego.speed, target_speeds=speeds)
        # The planned route (highway-env's ControlledVehicle.plan_route_to), also kept for
        # continuous control so that policies know which way to turn at junctions.
        self.route: list[tuple[str, str, int | None]] = [(frm, to, s.ego.lane)]
        if self.layout.ego_destination:
            path = net.shortest_path(to, self.layout.ego_destination)
            self.route += [(a, b, None) for a, b in zip(path, path[1:], strict=False)]
        if hasattr(ego, "route"):
            ego.route = list(self.route)
        size_object(ego, *CATEGORY_SIZES[self.config.ego_category][:2])
        return ego

    def _add(self, obj: TrafficVehicle | ScriptedObject) -> None:
        if obj.track_id in self._ids:
            raise ScenarioError(f"object id {obj.track_id!r} is already in use")
        self._ids[obj.track_id] = obj
        if population.is_vehicle(obj):
            if obj not in self.road.vehicles:
                self.road.vehicles.append(obj)
        elif obj not in self.road.objects:
            self.road.objects.append(obj)
        self.road.invalidate()

    def _require_reset(self) -> None:
        if self.road is None:
            raise RuntimeError("call reset() before using the bridge")

    def parse_action(self, action: object) -> dict[str, float] | str:
        """The ego controls ``action`` stands for; raises :class:`ActionError` and changes nothing."""
        if self.action_type == "continuous":
            return continuous_controls(action, self.config.actions)
        return meta_action(action)

    def step(self, action: object) -> list[SceneFrame]:
        """Apply one ego action, simulate one policy step, return its ``frames_per_step`` frames."""
        self._require_reset()
        self.ego_vehicle.act(self.parse_action(action))
        dt = self.scenario.sim_dt
        frames = []
        for _ in range(self.frames_per_step):
            self._prev_heading = self.ego_vehicle.heading
            for _ in range(self.scenario.substeps):
                self.road.act()
                self.road.step(dt)
                self._substeps += 1
            for v in population.departed(self.road, self.ego_vehicle, self.config.population):
                self.remove_object(v.track_id)
            self.frame_index += 1
            frames.append(self._frame())
        return frames

    # ------------------------------------------------------------------ state

    @property
    def time(self) -> float:
        return self._substeps * self.scenario.sim_dt

    @property
    def truncated(self) -> bool:
        """The scenario's duration is reached, or the ego has reached the end of the road network."""
        return self.time >= self.scenario.duration - 1e-9 or self.end_of_road

    @property
    def end_of_road(self) -> bool:
        """The ego is at the end of a lane the network does not continue (e.g. a roundabout's exit),
        still inside the lane's width: the map ends here, which is the end of the route rather than
        leaving the road."""
        ego = self.ego_vehicle
        _, to, _ = ego.lane_index
        if self.road.network.graph.get(to):
            return False
        longitudinal, lateral = ego.lane.local_coordinates(ego.position)
        return longitudinal >= ego.lane.length and abs(lateral) <= ego.lane.width_at(longitudinal) / 2

    @property
    def crashed(self) -> bool:
        return bool(self.ego_vehicle.crashed)

    @property
    def on_road(self) -> bool:
        """On a lane, or, where the road has a drivable area (a map), every corner of the ego's
        footprint inside it; running past the end of the network counts as the end of the route,
        not as leaving the road (at speed the ego can overshoot the lane's on-lane margin in one step)."""
        if self.end_of_road:
            return True
        if self.layout.drivable_area:
            return bool(points_in_polygons(self.ego_footprint(), self.layout.drivable_area).all())
        return bool(self.ego_vehicle.on_road)

    def ego_footprint(self) -> np.ndarray:
        """(4, 2) corners of the ego's footprint, our frame."""
        e = self.ego
        half_l, half_w = e.size[0] / 2, e.size[1] / 2
        c, s = math.cos(e.yaw), math.sin(e.yaw)
        local = np.array([[half_l, half_w], [half_l, -half_w], [-half_l, -half_w], [-half_l, half_w]])
        return np.array([e.x, e.y]) + local @ np.array([[c, s], [-s, c]])

    @property
    def lane_index(self) -> tuple[str, str, int]:
        return self.ego_vehicle.lane_index

    @property
    def num_lanes(self) -> int:
        frm, to, _ = self.ego_vehicle.lane_index
        return len(self.road.network.graph[frm][to])

    @property
    def lane_offset(self) -> float:
        """Ego's offset from its lane centre, metres, positive to the LEFT (our frame)."""
        return -float(self.ego_vehicle.lane.local_coordinates(self.ego_vehicle.position)[1])

    @property
    def map(self) -> MapGeometry:
        self._require_reset()
        return self._map

    @property
    def ego(self) -> EgoState:
        v = self.ego_vehicle
        dt = self.scenario.sim_dt * self.scenario.substeps
        yaw_rate = -math.remainder(v.heading - self._prev_heading, 2 * math.pi) / dt
        frm, to, k = v.lane_index
        return EgoState(
            x=float(v.position[0]),
            y=-float(v.position[1]),
            yaw=-float(v.heading),
            speed=float(v.speed),
            acceleration=float(v.action["acceleration"]),
            steering=-float(v.action["steering"]),
            yaw_rate=float(yaw_rate),
            size=CATEGORY_SIZES[self.config.ego_category],
            lane_id=f"{frm}>{to}>{k}",
        )

    def _others(self) -> list:
        ego, r2 = self.ego_vehicle, self.config.frame_radius_m**2
        out = []
        for o in [*self.road.vehicles, *self.road.objects]:
            d = o.position - ego.position
            if o is not ego and d[0] * d[0] + d[1] * d[1] <= r2:
                out.append(o)
        return out

    def _scene_object(self, o: TrafficVehicle | ScriptedObject) -> SceneObject:
        a = o.appearance
        h = a.size[2]
        heading, speed = float(o.heading), float(o.speed)
        x, y = o.position.tolist()
        vel = (speed * math.cos(heading), speed * math.sin(heading))  # highway-env's o.velocity, in math
        return SceneObject(
            track_id=o.track_id,
            category=a.category,
            box=Box3D(center=(x, -y, h / 2), size=a.size, yaw=-heading),
            color=a.color,
            color_name=a.color_name,
            description=a.description,
            velocity=(vel[0], -vel[1]),
            image_path=a.image_path,
            attributes={"source": "idm" if population.is_vehicle(o) and not o.scripted else "scripted"},
        )

    def _frame(self) -> SceneFrame:
        return SceneFrame(
            time=self.time,
            frame_index=self.frame_index,
            ego=self.ego,
            objects=tuple(self._scene_object(o) for o in self._others()),
            map=self._map,
            prompt=self.prompt,
            rig=self.rig,
            lidar=self.lidar,
            bev=self.bev,
            scenario=self.scenario.name,
        )

    def state_features(self, n_nearest: int = 5) -> np.ndarray:
        """highway-env Kinematics-style features, (1 + n_nearest, 7) float32 rows of
        [presence, x, y, vx, vy, cos_yaw, sin_yaw]. Row 0 is the ego in the world frame; the others
        are the nearest objects (within ``frame_radius_m``), relative to the ego and rotated into
        its frame, nearest first; missing rows are zeros."""
        self._require_reset()
        e = self.ego
        feats = np.zeros((1 + n_nearest, 7), dtype=np.float32)
        feats[0] = (
            1,
            e.x,
            e.y,
            e.speed * math.cos(e.yaw),
            e.speed * math.sin(e.yaw),
            math.cos(e.yaw),
            math.sin(e.yaw),
        )
        c, s = math.cos(e.yaw), math.sin(e.yaw)
        rows = []
        for o in self._others():
            dx, dy = o.position[0] - e.x, -o.position[1] - e.y
            vx, vy = o.velocity[0], -o.velocity[1]
            rel_yaw = -o.heading - e.yaw
            rows.append(
                (
                    dx * dx + dy * dy,
                    (
                        1,
                        c * dx + s * dy,
                        -s * dx + c * dy,
                        c * vx + s * vy,
                        -s * vx + c * vy,
                        math.cos(rel_yaw),
                        math.sin(rel_yaw),
                    ),
                )
            )
        rows.sort(key=lambda r: r[0])
        for k, (_, row) in enumerate(rows[:n_nearest]):
            feats[1 + k] = row
        return feats

    # ------------------------------------------------------------------ interactive objects

    def object_ids(self) -> list[str]:
        return list(self._ids)

    def _get(self, track_id: str) -> TrafficVehicle | ScriptedObject:
        self._require_reset()
        if not isinstance(track_id, str):
            raise population.UnknownObjectError(
                f"an object is named by its track id, a string, got {type(track_id).__name__}; "
                f"known ids: {sorted(self._ids)}"
            )
        if track_id not in self._ids:
            raise population.UnknownObjectError(f"no object {track_id!r}; known ids: {sorted(self._ids)}")
        return self._ids[track_id]

    def insert_object(self, spec: object) -> str:
        """Add a scripted object (an ``ObjectSpec`` or its dict form); its track's time starts now.
        Returns its track id."""
        self._require_reset()
        obj_spec = population.parse_spec(spec, "insert_object")
        if obj_spec.id in self._ids:
            raise ScenarioError(f"insert_object: id: {obj_spec.id!r} is already in use")
        self._add(population.make_scripted(self.road, self.layout, obj_spec, "insert_object"))
        return obj_spec.id

    def remove_object(self, track_id: str) -> None:
        obj = self._get(track_id)
        if obj in self.road.vehicles:
            self.road.vehicles.remove(obj)
        else:
            self.road.objects.remove(obj)
        del self._ids[track_id]
        self.road.invalidate()

    def edit_object(self, track_id: str, **changes: object) -> None:
        """Change an object's appearance (category, color, description, image, size), the target
        speed of a driving vehicle (``speed``), or a scripted object's ``track`` (restarts now)."""
        obj = self._get(track_id)
        new = population.edit(self.road, self.layout, obj, changes)
        if new is not obj:
            idx_list = self.road.vehicles if obj in self.road.vehicles else self.road.objects
            idx_list.remove(obj)
            del self._ids[track_id]
            self._add(new)
